"""The loop's guards (Dr.Jit 1.5's dr.clip propagates NaN, and Adam has no NaN guard of its
own), and what they count, without waiting for the device:

- a gradient component that is NaN/Inf is set to 0 before the step; with ``mask_updates``
  Adam then leaves that component and its moments alone (``nonfinite_steps``);
- after the step each variable is clipped into its bounds; components the step pushed out
  are counted (``clamped``; gains are clipped, not counted).

Their counts are symbolic sums, and each small variable's gradient is kept for the records;
all of it is evaluated in one launch with the next read of theta (``flush``).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..engine_api import SMALL
from .records import ParamRecord, Progress


class Guards:
    def __init__(self) -> None:
        self.pending: list[tuple[str, mi.Float]] = []   # counts not yet read
        self.stepped: list[dict[str, object]] = []      # gradients not yet read, per step

    def sanitize(self, opt, records: dict[str, ParamRecord], held: set[str]) -> None:
        """Non-finite gradient components to 0; each small variable's gradient kept (its width
        where a choice held the step: no step, and the zeroed gradient is not the images')."""
        bad = 0
        for key in records:
            value = opt[key]
            grad = dr.grad(value)
            finite = dr.isfinite(grad)
            dr.set_grad(value, dr.select(finite, grad, 0))
            bad += _true(~finite)
        self.pending.append(("nonfinite_steps", dr.select(bad > 0, 1.0, 0.0)))
        self.stepped.append({k: dr.width(opt[k]) if k in held else dr.grad(opt[k])
                             for k in records if dr.width(opt[k]) <= SMALL})

    def clip(self, opt, records: dict[str, ParamRecord]) -> None:
        """Each variable into its bounds, after the step."""
        for key, r in records.items():
            value = opt[key]
            lo, hi = r.bounds
            if not r.is_gain:
                self.pending.append(("clamped", _true((value < lo) | (value > hi))))
            opt[key] = dr.clip(value, lo, hi)

    def flush(self, progress: Progress, records: dict[str, ParamRecord], keep: int,
              also=()) -> None:
        """Evaluates the pending counts and gradients (and ``also``) into the counters and
        the records, which keep the last ``keep`` gradients (what diagnosis reads)."""
        grads = [g for stepped in self.stepped for g in stepped.values() if not isinstance(g, int)]
        dr.eval(*also, *(count for _, count in self.pending), *grads)
        for counter, count in self.pending:
            setattr(progress, counter, getattr(progress, counter) + round(count[0]))
        for stepped in self.stepped:
            for key, g in stepped.items():
                kept = records[key].gradients
                kept.append(np.full(g, np.nan) if isinstance(g, int)
                            else np.array(g, dtype=np.float64))
                del kept[:-keep]
        self.pending.clear()
        self.stepped.clear()


def _true(mask) -> mi.Float:
    """How many components of ``mask`` are true, as a symbolic sum: no launch, no wait."""
    return dr.sum(dr.select(dr.ravel(mask), 1.0, 0.0), axis=None, mode="symbolic")
