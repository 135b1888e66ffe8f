"""What to tell a user whose job did not converge, in words, from what the job saw."""

from __future__ import annotations

import numpy as np

from ..range_notes import bound_notes
from .parameters import ROUGHNESS_MIN


def diagnose(settings: dict, values: dict[str, np.ndarray], losses: list[float],
             nonfinite_steps: int, skipped_steps: int,
             trajectories: dict[str, np.ndarray] | None = None) -> list[str]:
    """``trajectories``: per parameter, its value at each iteration (iterations x components),
    for the parameters small enough to be recorded inline."""
    notes = []
    for key, s in settings.items():
        v = values.get(key)
        if v is None:
            continue
        # v is float32: 0.032 reads back as 0.0320000015, hence the tolerance of the bounds.
        if key.endswith("roughness.value") and np.all(v <= ROUGHNESS_MIN + 1e-6):
            notes.append(f"{key}: ended at {ROUGHNESS_MIN:g}, the principled BSDF's alpha floor "
                         "(0.001): a smoother surface would look the same, so the truth may "
                         "be anywhere below; compare alpha, not roughness")
            continue
        notes += bound_notes(key, v, s.lo, s.hi)
    for key, path in (trajectories or {}).items():
        s = settings.get(key)
        moving = still_moving(path, log=s is not None and s.log)
        if moving:
            a, b = moving
            notes.append(f"{key} was still moving when the job ended ({_short(a)} -> "
                         f"{_short(b)} over its last {_tail(len(path))} iterations): it has not "
                         "converged; more iterations, or a restart from this job's result, "
                         "would take it further")
    finite = [x for x in losses if np.isfinite(x)]
    if len(finite) >= 10:
        head, tail = np.mean(finite[:3]), np.mean(finite[-5:])
        if head > 0 and tail > 0.9 * head:
            how = "rose" if tail > 1.05 * head else "fell by less than 10%"
            notes.append(f"the loss {how} ({head:.3g} -> {tail:.3g}): check that the "
                         "references show this scene from these sensors, or try more "
                         "iterations, more spp or a smaller or larger learning rate")
    if nonfinite_steps:
        notes.append(f"{nonfinite_steps} step(s) had NaN/Inf gradient components; they were "
                     "zeroed, and those components kept their values")
    if skipped_steps:
        notes.append(f"{skipped_steps} step(s) were skipped: the loss was NaN/Inf")
    return notes


def _tail(n: int) -> int:
    return max(5, n // 5)


def _short(v: np.ndarray) -> str:
    return ", ".join(f"{x:.4g}" for x in np.ravel(v)[:3]) + (" ..." if np.size(v) > 3 else "")


def still_moving(path: np.ndarray, log: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
    """(earlier, later) means when the last fifth of a trajectory drifted steadily: the two
    halves of that window differ by more than 1% of the value (relative in log space) and by
    more than three standard errors of their noise. A converged parameter jitters around its
    optimum, with no drift between the halves."""
    path = np.asarray(path, dtype=np.float64)
    n = _tail(len(path))
    if len(path) < 20 or path.ndim != 2:
        return None
    window = np.log(np.maximum(path[-n:], 1e-30)) if log else path[-n:]
    first, second = window[: n // 2], window[n // 2:]
    drift = np.abs(second.mean(axis=0) - first.mean(axis=0))
    noise = np.sqrt(first.var(axis=0) / len(first) + second.var(axis=0) / len(second))
    scale = 0.01 if log else 0.01 * np.maximum(np.abs(window).mean(axis=0), 1e-3)
    if np.any((drift > scale) & (drift > 3 * noise)):
        return path[-n:][: n // 2].mean(axis=0), path[-n:][n // 2:].mean(axis=0)
    return None
