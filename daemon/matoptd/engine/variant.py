"""Choosing the Mitsuba variant and the Dr.Jit environment, once, before anything renders."""

from __future__ import annotations

import glob
import os
import platform
import re
from pathlib import Path

PREFERRED = ("cuda_ad_rgb", "llvm_ad_rgb")


def configure_environment(data_dir: Path) -> None:
    """Environment Dr.Jit reads when it is first imported.

    The kernel cache goes under the data dir (a daemon should not share ``~/.drjit`` with a
    user's scripts). Dr.Jit 1.5 aborts on LLVM 14/15 ("Cannot select ... fminimum"), and left
    alone it may pick one of those, so unless ``DRJIT_LIBLLVM_PATH`` is set we point it at the
    newest libLLVM >= 16 we can find.
    """
    os.environ.setdefault("DRJIT_CACHE_DIR", str(Path(data_dir) / "kernel-cache"))
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        llvm = find_libllvm()
        if llvm:
            os.environ["DRJIT_LIBLLVM_PATH"] = llvm


def find_libllvm() -> str | None:
    """The newest system libLLVM with major version >= 16, or None."""
    candidates = []
    for pattern in ("/usr/lib/*/libLLVM*.so*", "/usr/lib/llvm-*/lib/libLLVM*.so*",
                    "/usr/lib64/libLLVM*.so*", "/usr/local/lib/libLLVM*.so*"):
        for path in glob.glob(pattern):
            m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
            if m and int(m.group(1)) >= 16:
                candidates.append((int(m.group(1)), path))
    return max(candidates)[1] if candidates else None


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
            out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                                 capture_output=True, text=True, timeout=10).stdout.strip()
            return out.splitlines()[0] if out else "CUDA device"
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
    return f"CPU: {cpu}, {os.cpu_count()} threads (LLVM: {llvm})"
