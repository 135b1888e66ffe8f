"""What a job says about parameter ranges: a value that ended on a bound, or a start value
that had to be clipped into the range. Pure numpy, shared by the daemon and the engine."""

from __future__ import annotations

import numpy as np

# float32 holds 7 significant digits: a value the clip left at a bound reads back within a
# few units in the last place of it (1000.0 as 999.99994), and a bound near 0 within 1e-6.
RTOL = 4 * float(np.finfo(np.float32).eps)
ATOL = 1e-6


def at_bound(values: np.ndarray, bound: float) -> np.ndarray:
    """Which components sit on ``bound``, within float32 precision (none for an infinite one)."""
    if not np.isfinite(bound):
        return np.zeros(np.shape(values), dtype=bool)
    return np.isclose(np.asarray(values, dtype=np.float64), bound, rtol=RTOL, atol=ATOL)


def bound_notes(key: str, values: np.ndarray, lo: float, hi: float) -> list[str]:
    """One note per bound that components of ``key`` ended on, with what to do about it."""
    notes = []
    for bound, name, beyond in ((lo, "lower", "below"), (hi, "upper", "above")):
        at = int(np.sum(at_bound(values, bound)))
        if at:
            notes.append(
                f"{key}: {at} of {np.size(values)} component(s) ended on its {name} bound "
                f"{bound:g}: the images may want a value {beyond} it (or do not constrain it); "
                f"widen its range (--range {key}=MIN:MAX, within the legal range) if the truth "
                f"may lie {beyond}, or fix the parameter at a known value (leave it out of "
                "--param)")
    return notes


def clip_note(key: str, start: np.ndarray, lo: float, hi: float, source: str) -> str | None:
    """A start value outside [lo, hi] is clipped into it before the first iteration: which
    parameter, from what to what. ``source`` says where the value came from ("the initial
    value", "the result of jobs/x")."""
    start = np.asarray(start, dtype=np.float64)
    clipped = np.clip(start, lo, hi)
    moved = clipped != start
    if not moved.any():
        return None
    if start.size == 1:
        change = f"from {start.item():g} to {clipped.item():g}"
    else:
        i = int(np.argmax(np.abs(clipped - start)))
        change = (f"{int(moved.sum())} of {start.size} components, e.g. component {i} from "
                  f"{start[i]:g} to {clipped[i]:g}")
    return (f"{key}: {source} lies outside the job's range [{lo:g}, {hi:g}] and was clipped "
            f"into it ({change})")
