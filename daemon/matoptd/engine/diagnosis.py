"""What to tell a user whose job did not converge, in words, from what the job saw."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..range_notes import bound_notes


@dataclass(frozen=True)
class Kept:
    """What the diagnosis reads of a parameter, from the choices in force: the range its value
    is kept in, the floor it is shown at (0: none), whether it is stepped as log v."""

    lo: float
    hi: float
    floor: float = 0.0
    log: bool = False


@dataclass(frozen=True)
class Wander:
    """How far a parameter wandered where the history found it undecided by its wandering
    (a drift on noise, two parameters moving in step at a level loss), on the value's scale,
    the note that says so, and what that note becomes where its interval is widened to cover
    the wander: then it is scatter the result's interval includes, not a contradiction of it.
    ``limit``: the widest standard error that still says something of the value (wider, it
    is not determined)."""

    moved: np.ndarray
    note: str
    within: str
    limit: np.ndarray | float = np.inf


@dataclass
class Diagnosis:
    """The notes, and the parameters they say these images do not decide, each with why in a
    few words (what a result's verdict on it says: engine/verdicts.py), and how far those
    found so by their wandering wandered."""

    notes: list[str] = field(default_factory=list)
    undecided: dict[str, str] = field(default_factory=dict)
    wander: dict[str, Wander] = field(default_factory=dict)


DECIDERS = ("more views (another sensor that sees them), a reference that shows what "
            "separates them, or a fixed value for one of them (leave it out of the selection)")
DECIDER = ("more views (another sensor that sees it), larger images or more samples, or a "
           "fixed value (leave it out of the selection)")


def diagnose(settings: dict[str, Kept], values: dict[str, np.ndarray], losses: list[float],
             nonfinite_steps: int, skipped_steps: int,
             trajectories: dict[str, np.ndarray] | None = None,
             truth_errors: dict[str, list[float]] | None = None,
             gradients: dict[str, list[np.ndarray]] | None = None,
             traded: set[frozenset[str]] = frozenset(),
             undetermined: set[str] = frozenset()) -> Diagnosis:
    """``trajectories``: per parameter, its value at each iteration (iterations x components),
    for the parameters small enough to be recorded inline, and the mean over components for
    the others (textures, grids). ``truth_errors``: per parameter with a ground truth, its
    relative error at each iteration. ``gradients``: per small parameter, the gradient of
    each step (the latest last). ``traded`` and ``undetermined``: the pairs and parameters
    the standard errors already name (engine/uncertainty.py), whose notes from the history
    would say less."""
    out = undecided(losses, trajectories or {}, truth_errors or {}, traded, undetermined)
    notes = out.notes
    for key, s in settings.items():
        v = values.get(key)
        if v is None:
            continue
        # v is float32: 0.0318 reads back a little off, hence the tolerance of the bounds.
        if s.floor and np.all(v <= s.floor + 1e-6):
            n = _tail(len((trajectories or {}).get(key, ())))
            notes.append(floor_note(key, s.floor, (gradients or {}).get(key, [])[-n:]))
            continue
        notes += bound_notes(key, v, s.lo, s.hi)
    trajectories = trajectories or {}
    for key, (a, b) in moving(settings, trajectories).items():
        n = _tail(len(trajectories[key]))
        drift = f"{_short(a)} -> {_short(b)} over its last {n} iterations"
        gradient = steered((gradients or {}).get(key, [])[-n:])
        if gradient is not None and not gradient[0]:
            _, mean, se = gradient
            notes.append(f"{key} drifted ({drift}) on noise: its gradient over those steps "
                         f"averaged {_short(mean)} (standard error {_short(se)}), no consistent "
                         "sign, so the images did not steer it there; what would decide it: "
                         f"{DECIDER}")
            if key not in out.undecided:
                moved = np.abs(np.asarray(b) - np.asarray(a))
                out.undecided[key] = "it drifted on gradients of no consistent sign"
                out.wander[key] = Wander(moved, notes[-1], (
                    f"{key} drifted by {_short(moved)} over its last {n} iterations on "
                    "gradients of no consistent sign: its interval is at least as wide, so "
                    "that it includes this scatter"))
        else:
            notes.append(f"{key} was still moving when the job ended ({drift}): it has not "
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
    for key, w in out.wander.items():
        if key in settings and key in values:
            out.wander[key] = replace(w, limit=widest(settings[key], values[key]))
    return out


def widest(kept: Kept, value: np.ndarray) -> np.ndarray:
    """Per component, the widest standard error with which an interval still says something
    of a value: a quarter of its range (in log space of its log-range, times the value; a
    quarter of the value where that range is unbounded)."""
    v = np.abs(np.asarray(value, dtype=np.float64))
    lower = max(kept.lo, kept.floor)
    if kept.log:
        span = math.log(kept.hi / lower) if lower > 0 and math.isfinite(kept.hi) else 1.0
        return 0.25 * span * v
    span = kept.hi - kept.lo
    return np.full(v.shape, 0.25 * (span if math.isfinite(span) else 1.0))


def floor_note(key: str, floor: float, gradients: list[np.ndarray]) -> str:
    """What a principled roughness ending at the floor it is shown at means, from the sign of
    its gradient there over the last steps (positive: the images push it lower)."""
    said = (f"{key}: ended at {floor:g}, the principled BSDF's alpha floor (0.001): a "
            "smoother surface looks the same")
    gradient = steered(gradients)
    if gradient is None:
        return (f"{said}, so the truth may be anywhere below; compare alpha, not roughness")
    pushed, mean, se = gradient
    if pushed and np.all(mean >= 0):
        return (f"{said}, and the images kept pressing it there (gradient {_short(mean)}, "
                f"standard error {_short(se)}), so the truth is at or below it; compare alpha, "
                "not roughness")
    if pushed:
        return (f"{said}, but the images were pulling it up (gradient {_short(mean)}, standard "
                f"error {_short(se)}): it had not converged; more iterations, or a restart "
                "from this job's result, would take it further")
    return (f"{said}, and its gradient there had no consistent sign (mean {_short(mean)}, "
            f"standard error {_short(se)}): the images do not tell the floor from a slightly "
            f"rougher surface; what would decide it: {DECIDER}")


def undecided(losses: list[float], trajectories: dict[str, np.ndarray],
              truth_errors: dict[str, list[float]],
              traded: set[frozenset[str]] = frozenset(),
              undetermined: set[str] = frozenset()) -> Diagnosis:
    """Where the images do not decide: a parameter that moves away from a given truth while
    the render keeps matching, and pairs of parameters that trade off (unless the standard
    errors' correlations name them: ``traded``), and parameters that never moved (unless
    found not determined)."""
    out = Diagnosis()
    notes, found = out.notes, out.undecided
    for key, first, best, last in drifts_from_truth(losses, truth_errors):
        notes.append(f"{key}: the render matches the references as well as it did, but the "
                     f"error against the given truth grew from {best:.3g} (its lowest) to "
                     f"{last:.3g} (started at {first:.3g}): these images do not decide it; what "
                     f"would: {DECIDER}")
        found.setdefault(key, "the render kept matching while its error against the given "
                              "truth grew")
    for a, b, r, spans in trade_offs(losses, trajectories):
        if frozenset((a, b)) in traded:
            continue
        how = "rises as the other falls" if r < 0 else "moves with the other"
        notes.append(f"{a} and {b} trade off: over the last iterations one {how} (correlation "
                     f"{r:+.2f}) while the loss stays level, so the images do not tell them "
                     f"apart; what would decide them: {DECIDERS}")
        within = (f"{a} and {b} wandered in step at a level loss (correlation {r:+.2f}): "
                  "their intervals are at least as wide, so that they include this scatter")
        for one, other, span in ((a, b, spans[0]), (b, a, spans[1])):
            if one not in found:
                found[one] = f"it trades off with {other} at a level loss"
                out.wander[one] = Wander(np.array([span]), notes[-1], within)
    for key in unmoved(trajectories, losses):
        if key in undetermined:
            continue
        found.setdefault(key, "it never moved: the images carry no gradient for it")
        notes.append(f"{key} hardly moved while the loss fell: the images carry no gradient "
                     "for it (light that would show it may never reach the camera, e.g. "
                     "transmission at a small max_depth); what would decide it: a deeper "
                     f"max_depth, {DECIDER}")
    return out


def _smooth(x: np.ndarray, k: int = 5) -> np.ndarray:
    k = max(1, min(k, len(x)))
    return np.convolve(x, np.ones(k) / k, mode="valid")


def _level(losses: list[float]) -> bool:
    """Whether the loss is level over the second half of the history: its last quarter's
    mean within 25% of the quarter before (noise, not descent)."""
    finite = np.array([x for x in losses if np.isfinite(x)], dtype=np.float64)
    if len(finite) < 20:
        return False
    q = len(finite) // 4
    before, after = finite[-2 * q:-q].mean(), finite[-q:].mean()
    return before > 0 and after > 0.75 * before


def drifts_from_truth(losses: list[float], truth_errors: dict[str, list[float]],
                      ) -> list[tuple[str, float, float, float]]:
    """(key, first, lowest, last error) for each parameter whose error against the truth
    ended well above its lowest (by at least 3% of the truth and three times the jitter of
    its last tenth, and by half again or by 5%) while the loss ended no higher than where it
    was at that lowest: the images stopped steering it, or steered it away."""
    out = []
    finite = [x for x in losses if np.isfinite(x)]
    if len(finite) < 10:
        return out
    smooth = _smooth(np.asarray(finite, dtype=np.float64))
    for key, errors in truth_errors.items():
        e = np.asarray(errors, dtype=np.float64)
        if len(e) < 10 or not np.all(np.isfinite(e)):
            continue
        at = int(np.argmin(e))
        tail = e[-max(3, len(e) // 10):]
        last, jitter = float(tail.mean()), float(tail.std())
        grew = last - e[at]
        loss_then = smooth[min(at, len(smooth) - 1)]
        if (grew > max(0.03, 3 * jitter) and (last > 1.5 * e[at] or grew > 0.05)
                and smooth[-1] <= 1.1 * loss_then):
            out.append((key, float(e[0]), float(e[at]), last))
    return out


def _series(path: np.ndarray) -> np.ndarray:
    """A trajectory as one number per iteration: the mean over its components."""
    path = np.asarray(path, dtype=np.float64)
    return path.reshape(len(path), -1).mean(axis=1)


def trade_offs(losses: list[float], trajectories: dict[str, np.ndarray],
               min_correlation: float = 0.8
               ) -> list[tuple[str, str, float, tuple[float, float]]]:
    """(a, b, correlation, how far each wandered: the span of its smoothed mean) for pairs of
    parameters that both wandered over the second half of the history (by more than 2% of
    their value, turning back at least once) in step with each other while the loss stayed
    level: a valley the images cannot resolve. A parameter
    still heading one way is converging (or not yet done), not wandering: two of those move
    in step too, but that says nothing about the images."""
    if not _level(losses):
        return []
    moving = {}
    for key, path in trajectories.items():
        x = _series(path)
        if len(x) < 40 or not np.all(np.isfinite(x)):
            continue
        window = _smooth(x[-len(x) // 2:])
        span = window.max() - window.min()
        travelled = np.sum(np.abs(np.diff(window)))
        net = abs(window[-1] - window[0])
        if span > 0.02 * max(abs(window.mean()), 1e-3) and travelled > 1.5 * net + 0.5 * span:
            moving[key] = window
    out = []
    keys = list(moving)
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            n = min(len(moving[a]), len(moving[b]))
            r = float(np.corrcoef(moving[a][-n:], moving[b][-n:])[0, 1])
            if np.isfinite(r) and abs(r) >= min_correlation:
                out.append((a, b, r, tuple(float(np.ptp(moving[k])) for k in (a, b))))
    return out


def unmoved(trajectories: dict[str, np.ndarray], losses: list[float]) -> list[str]:
    """Parameters that never moved (all components within 1e-5 relative of their start)
    while the loss fell by more than half: nothing in the images responds to them."""
    finite = [x for x in losses if np.isfinite(x)]
    if len(finite) < 10 or not np.mean(finite[-3:]) < 0.5 * np.mean(finite[:3]):
        return []
    out = []
    for key, path in trajectories.items():
        p = np.asarray(path, dtype=np.float64).reshape(len(path), -1)
        if len(p) >= 10 and np.all(np.abs(p - p[0]) <= 1e-5 * np.maximum(np.abs(p[0]), 1e-3)):
            out.append(key)
    return out


def _tail(n: int) -> int:
    return max(5, n // 5)


def _short(v: np.ndarray) -> str:
    return ", ".join(f"{x:.4g}" for x in np.ravel(v)[:3]) + (" ..." if np.size(v) > 3 else "")


def moving(settings: dict, trajectories: dict[str, np.ndarray]
           ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The parameters ``still_moving`` at the end: (earlier, later) means of each."""
    out = {}
    for key, path in trajectories.items():
        s = settings.get(key)
        ends = still_moving(path, log=s is not None and s.log)
        if ends:
            out[key] = ends
    return out


def steered(gradients: list[np.ndarray]) -> tuple[bool, np.ndarray, np.ndarray] | None:
    """(steered, mean, standard error) of the gradients of some steps, per component:
    steered when some component's mean is over two standard errors from 0. Each step's
    gradient comes from samples of its own, so a drift on gradients without a consistent sign
    is Adam stepping on noise (its step is as long on noise as on signal), not descent."""
    if len(gradients) < 5:
        return None
    g = np.array([np.ravel(x) for x in gradients], dtype=np.float64)
    g = g[np.all(np.isfinite(g), axis=1)]  # a held step's (NaN) is not the images' gradient
    if len(g) < 5:
        return None
    mean, se = g.mean(axis=0), g.std(axis=0, ddof=1) / np.sqrt(len(g))
    return bool(np.any(np.abs(mean) > 2 * se)), mean, se


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
