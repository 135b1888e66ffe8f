"""What the workers run on, decided without importing Dr.Jit: CUDA devices (from nvidia-smi),
CPU cores to split between CPU workers, the libLLVM Dr.Jit's CPU backend should load, and the
environment a worker starts with."""

from __future__ import annotations

import glob
import os
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..cores import core_ranges
from . import sizing


@dataclass(frozen=True)
class Placement:
    """Where one worker runs: a CUDA device (``cuda`` is its index as CUDA_VISIBLE_DEVICES
    takes it) or a set of CPU cores, rendering with ``threads`` threads."""

    cuda: str | None
    cores: tuple[int, ...]
    threads: int
    sizing: str = ""  # how many workers share the device, and why (workers/sizing.py)

    def describe(self) -> str:
        if self.cuda is not None:
            return f"CUDA device {self.cuda}"
        return f"CPU: {self.threads} thread(s) on cores {core_ranges(self.cores)}"


def cuda_devices() -> list[str]:
    """Indices of the NVIDIA GPUs nvidia-smi lists (none when it is absent or fails)."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=index", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return []
    if out.returncode != 0:
        return []
    return [line.strip() for line in out.stdout.splitlines() if line.strip().isdigit()]


def gpu_free_memory(device: str) -> int | None:
    """Free bytes of a CUDA device (index or UUID) as nvidia-smi reads them; None when it
    cannot."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=memory.free", "--format=csv,noheader,"
                              "nounits", "-i", device], capture_output=True, text=True,
                             timeout=20)
    except (OSError, subprocess.SubprocessError):
        return None
    try:
        return int(out.stdout.split()[0]) << 20 if out.returncode == 0 else None  # MiB
    except (IndexError, ValueError):
        return None


def cpu_cores() -> list[int]:
    return sorted(os.sched_getaffinity(0))


def split_cores(cores: list[int], workers: int) -> list[tuple[int, ...]]:
    """``workers`` disjoint, contiguous sets of cores, as even as they can be; with more
    workers than cores, cores are shared round-robin."""
    if workers <= len(cores):
        size, extra = divmod(len(cores), workers)
        out, at = [], 0
        for i in range(workers):
            n = size + (i < extra)
            out.append(tuple(cores[at:at + n]))
            at += n
        return out
    return [(cores[i % len(cores)],) for i in range(workers)]


def reserve_cores(n: int) -> list[int]:
    """Pins every thread of this process to the first ``n`` cores it may run on and returns
    the others, for the workers: the server's gRPC threads and a machine's other services
    then never take a render thread's core, nor a worker theirs."""
    cores = cpu_cores()
    if not 0 < n < len(cores):
        raise ValueError(f"{n} core(s) for the server leave none of the {len(cores)} this "
                         f"process may use ({core_ranges(cores)}) to the workers")
    for task in os.listdir("/proc/self/task"):  # threads started before this one, too
        os.sched_setaffinity(int(task), cores[:n])
    return cores[n:]


def lower_priority(by: int, keep: set[int]) -> int:
    """Lowers every thread of this process but ``keep`` by ``by`` nice levels (to at most 19)
    and returns how many it lowered. The server's threads (gRPC, handlers) then give way to
    the render threads on cores they share, so status traffic takes its CPU from the server
    rather than from the jobs. ``keep``: the lanes' threads, which start the worker processes
    (a process starts with the nice value of the thread that forked it, and an unprivileged
    one cannot lower it back), and the monitor's, which stops them. Threads started later by a lowered one inherit its value."""
    lowered = 0
    for task in os.listdir("/proc/self/task"):
        tid = int(task)
        if tid in keep:
            continue
        try:
            now = os.getpriority(os.PRIO_PROCESS, tid)
            if now < 19:
                os.setpriority(os.PRIO_PROCESS, tid, min(19, now + by))
                lowered += 1
        except (ProcessLookupError, PermissionError):
            pass  # a thread that ended meanwhile
    return lowered


def placements(devices: list[str] | None, workers: int | None, variant: str | None,
               cores: list[int] | None = None, per_device: int | None = None,
               max_samples: int = 1 << 26,
               free_memory: Callable[[str], int | None] = gpu_free_memory) -> list[Placement]:
    """Workers on each CUDA device (``devices``, else every one nvidia-smi lists or
    CUDA_VISIBLE_DEVICES names), as many as ``per_device`` or, when None, as its free memory
    holds (``sizing.for_device``), unless CPU workers are asked for (``workers``, or an LLVM
    ``variant``) or there is no GPU: then ``workers`` (default 1) CPU workers with the
    ``cores`` (default: all this process may use) split between them, or ``per_device``
    workers that each render on all of them."""
    cores = cores or cpu_cores()
    cpu_asked = workers is not None or (variant or "").startswith(("llvm", "scalar"))
    if devices is None and not cpu_asked:
        # An administrator's CUDA_VISIBLE_DEVICES names the devices the daemon may use.
        visible = os.environ.get("CUDA_VISIBLE_DEVICES", "").strip()
        devices = [d.strip() for d in visible.split(",") if d.strip()] if visible \
            else cuda_devices()
    if devices and not cpu_asked:
        out = []
        for d in dict.fromkeys(devices):  # a device named twice: --devices 0,0
            named = devices.count(d)
            asked = named if named > 1 else per_device
            # nvidia-smi is read only when the memory decides (it takes a while on some hosts)
            free = free_memory(d) if asked is None else None
            size = sizing.for_device(free, max_samples, asked)
            out += [Placement(d, tuple(cores), len(cores), size.why)] * size.count
        return out
    if per_device is not None and workers is None:
        why = f"{per_device} sharing the CPU's cores (--workers-per-device {per_device})"
        return [Placement(None, tuple(cores), len(cores), why)] * per_device
    return [Placement(None, c, len(c)) for c in split_cores(cores, workers or 1)]


def find_libllvm() -> str | None:
    """The newest system libLLVM with major version >= 16, or None. Dr.Jit 1.5 aborts on LLVM
    14/15 ("Cannot select ... fminimum"), and left alone it may pick one of those."""
    candidates = []
    for pattern in ("/usr/lib/*/libLLVM*.so*", "/usr/lib/llvm-*/lib/libLLVM*.so*",
                    "/usr/lib64/libLLVM*.so*", "/usr/local/lib/libLLVM*.so*"):
        for path in glob.glob(pattern):
            m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
            if m and int(m.group(1)) >= 16:
                candidates.append((int(m.group(1)), path))
    return max(candidates)[1] if candidates else None


# numpy's BLAS in a worker multiplies matrices of a few dozen columns (the standard errors);
# threads of its own only fight the render threads for the cores: a crossed product of J's
# estimates at 128x96 took 919 ms with them on a busy machine, 9 ms on one thread.
NUMPY_ENVIRONMENT = {"OPENBLAS_NUM_THREADS": "1"}


def worker_environment(data_dir: Path, placement: Placement) -> dict[str, str]:
    """The environment of a worker process. Dr.Jit reads its cache dir and libLLVM once, at
    import. The kernel cache goes under the data dir (a daemon should not share ``~/.drjit``
    with a user's scripts); a CUDA worker sees only its own device."""
    env = dict(os.environ)
    env.setdefault("DRJIT_CACHE_DIR", str(Path(data_dir) / "kernel-cache"))
    if "DRJIT_LIBLLVM_PATH" not in env:
        llvm = find_libllvm()
        if llvm:
            env["DRJIT_LIBLLVM_PATH"] = llvm
    if placement.cuda is not None:
        env["CUDA_VISIBLE_DEVICES"] = placement.cuda
    env["PYTHONUNBUFFERED"] = "1"
    for name, value in NUMPY_ENVIRONMENT.items():
        env.setdefault(name, value)
    return env


def total_memory() -> int:
    """Physical memory in bytes."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def parse_size(text: str) -> int:
    """'8G', '512M', '1.5GiB', '1000000' -> bytes."""
    m = re.fullmatch(r"\s*([0-9.]+)\s*([kKmMgGtT]?)(?:i?[bB])?\s*", text)
    if not m:
        raise ValueError(f"'{text}' is not a size (e.g. 8G, 512M)")
    return int(float(m.group(1)) * 1024 ** " KMGT".index((m.group(2) or " ").upper()))
