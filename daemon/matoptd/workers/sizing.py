"""How many worker processes share one device (``matoptd --workers-per-device auto|N``).

A small job leaves most of a large GPU idle, and two worker processes on one H100 ran small
jobs at 2.06x the rate of one; as Triton's instance groups do, a GPU then runs as many workers
as its memory holds. Each worker is sized for the largest job admission lets in (a render call
of ``--max-samples`` samples: every admitted job is at most that), so any job fits any worker;
a smaller ``--max-samples`` packs more workers on a device. The constants are conservative
estimates for CUDA variants (a GPU measurement of them is still owed); a CPU-only host keeps
one worker unless a number is given, since its cores, not its memory, are the limit.
"""

from __future__ import annotations

from dataclasses import dataclass

from matopt_api.costs import format_size

WORKER_BYTES = 1 << 30    # a CUDA worker at rest: its context, Dr.Jit's kernels, Mitsuba, a scene
BYTES_PER_SAMPLE = 64     # of a render call in flight (the wavefront's per-sample state)
HEADROOM = 0.1            # of the free memory left to other processes and fragmentation
MAX_PER_DEVICE = 8        # past this, more processes only queue on the device


@dataclass(frozen=True)
class Sizing:
    """Workers on one device, and why that many (``matopt info`` shows it)."""

    count: int
    why: str


def parse(text: str) -> int | None:
    """``--workers-per-device``: "auto" (None) or a number >= 1."""
    if text.strip().lower() == "auto":
        return None
    try:
        n = int(text)
    except ValueError:
        raise ValueError(f"'{text}' is neither 'auto' nor a number") from None
    if n < 1:
        raise ValueError(f"must be 'auto' or >= 1, got {n}")
    return n


def per_worker(max_samples: int) -> int:
    """Device memory one worker may need: at rest, plus the largest admitted render call."""
    return WORKER_BYTES + max_samples * BYTES_PER_SAMPLE


def for_device(free: int | None, max_samples: int, asked: int | None) -> Sizing:
    """The workers one device runs: ``asked`` when given, else as many as ``free`` bytes of
    its memory hold (``per_worker`` each, ``HEADROOM`` left over), between 1 and
    ``MAX_PER_DEVICE``; one when its free memory is unknown."""
    if asked is not None:
        return Sizing(asked, f"{asked} per device (--workers-per-device {asked})")
    if free is None:
        return Sizing(1, "1 per device (auto: its free memory could not be read)")
    need = per_worker(max_samples)
    fits = int(free * (1 - HEADROOM) // need)
    count = max(1, min(MAX_PER_DEVICE, fits))
    why = (f"{count} per device (auto: {format_size(free)} free, {format_size(need)} per "
           f"worker for a render call of up to {max_samples:,} samples"
           + (f", at most {MAX_PER_DEVICE}" if fits > MAX_PER_DEVICE else "")
           + (", though not even one fits" if fits < 1 else "") + ")")
    return Sizing(count, why)
