"""What optimizing a large parameter costs, in words: for listing a scene's parameters (the
client, from their shapes) and for a job that selects one (the daemon's note and warning).

A parameter of n float32 values holds, while a job optimizes it: the value, its gradient and
Adam's two moments on the renderer's device (16 bytes a value), and in the worker's memory the
values read back each iteration plus the best and last iterations' (12 bytes); a checkpoint
stores value, moments, best and last (20 bytes). Each iteration, the step, the NaN guard, the
clip and the read-back take about 10 ns a value on the 2-core CPU backend, where a sample of a
``prb`` render with its backward pass takes about 5 us: a value costs about 1/500 of a sample.
Rough, since a render's cost per sample varies with the scene; the render usually dominates.
"""

from __future__ import annotations

import math
from typing import Sequence

# From this many values on a parameter is called large (64 MiB on the device while optimized):
# a 1,200 x 1,200 RGB texture. Below it, its cost is small next to the film's.
LARGE_VALUES = 1 << 22
DEVICE_BYTES_PER_VALUE = 16      # value, gradient, Adam's first and second moments (float32)
HOST_BYTES_PER_VALUE = 12        # values read back each iteration, best and last kept
CHECKPOINT_BYTES_PER_VALUE = 20  # value, two moments, best and last
VALUES_PER_SAMPLE = 500          # values whose update costs what one rendered sample does


def format_size(n: float) -> str:
    """Bytes as people read them: 812 B, 3.4 KiB, 8.0 GiB."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError("unreachable")


def value_count(shape: Sequence[int]) -> int:
    return math.prod(shape) if shape else 1


def is_large(shape: Sequence[int]) -> bool:
    return value_count(shape) >= LARGE_VALUES


def parameter_cost(key: str, shape: Sequence[int],
                   samples_per_iteration: int | None = None) -> str:
    """One sentence: the memory a parameter takes while optimized and its share of an
    iteration's time; ``samples_per_iteration`` (a job's renders) gives that share as a
    percentage, else as the render it equals."""
    n = value_count(shape)
    samples = n / VALUES_PER_SAMPLE
    if samples_per_iteration:
        time = (f"its update adds about {100 * samples / samples_per_iteration:.0f}% to the "
                f"time of the iteration's renders ({samples_per_iteration:,} samples)")
    else:
        side = max(1, round(math.sqrt(samples)))
        time = (f"its update takes about as long as rendering {samples:,.0f} samples (a "
                f"{side}x{side} film at 1 spp)")
    return (f"'{key}' has {n:,} values: optimizing it takes "
            f"{format_size(n * DEVICE_BYTES_PER_VALUE)} on the renderer's device (value, "
            f"gradient, Adam's moments) and {format_size(n * HOST_BYTES_PER_VALUE)} of "
            f"worker memory; each checkpoint writes {format_size(n * CHECKPOINT_BYTES_PER_VALUE)};"
            f" each iteration {time}")
