"""Choosing the Mitsuba variant, once per worker process, before anything renders."""

from __future__ import annotations

import os
import platform

from ..cores import core_ranges

PREFERRED = ("cuda_ad_rgb", "llvm_ad_rgb")


def select(requested: str | None) -> tuple[str, str]:
    """Sets the variant (``requested``, else CUDA when a device works, else LLVM).

    Returns the variant and a description of the device it runs on.
    """
    import drjit as dr
    import mitsuba as mi

    if requested:
        if requested not in mi.variants():
            raise ValueError(f"variant '{requested}' is not available; this Mitsuba build has "
                             f"{', '.join(mi.variants())}")
        if requested.startswith(("cuda", "llvm")) and not _backend_works(dr, requested):
            raise RuntimeError(f"variant '{requested}' does not work here: Dr.Jit finds no "
                               + ("usable CUDA device" if requested.startswith("cuda") else
                                  "usable libLLVM >= 16 (apt-get install libllvm19, or set "
                                  "DRJIT_LIBLLVM_PATH)"))
        mi.set_variant(requested)
    else:
        usable = [v for v in PREFERRED if v in mi.variants() and _backend_works(dr, v)]
        if not usable:
            raise RuntimeError("neither CUDA nor LLVM works for Dr.Jit here; install libLLVM "
                               ">= 16 (e.g. apt-get install libllvm19) or set "
                               "DRJIT_LIBLLVM_PATH")
        mi.set_variant(usable[0])
    variant = mi.variant()
    return variant, _device(variant)


def _backend_works(dr, variant: str) -> bool:
    backend = dr.JitBackend.CUDA if variant.startswith("cuda") else dr.JitBackend.LLVM
    try:
        return bool(dr.has_backend(backend))
    except Exception:
        return False


def _device(variant: str) -> str:
    if variant.startswith("cuda"):
        try:
            import subprocess
            index = os.environ.get("CUDA_VISIBLE_DEVICES", "0").split(",")[0]
            out = subprocess.run(["nvidia-smi", "-i", index, "--query-gpu=name",
                                  "--format=csv,noheader"],
                                 capture_output=True, text=True, timeout=10).stdout.strip()
            name = out.splitlines()[0] if out else "CUDA device"
            return f"{name} (CUDA device {index})"
        except Exception:
            return "CUDA device"
    cpu = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    llvm = os.environ.get("DRJIT_LIBLLVM_PATH", "system libLLVM")
    cores = sorted(os.sched_getaffinity(0))
    return f"CPU: {cpu}, {len(cores)} core(s) {core_ranges(cores)} (LLVM: {llvm})"

