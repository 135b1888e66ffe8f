"""Starts compared (JobSettings.starts): where a job's probes begin, how long they run, and
whether their ends say that the images allow several answers.

A standard error describes the basin a job ended in: how far its value may be from the
minimum of that basin. It cannot know of other basins. Probes from diverse starts can: where
two of them end at losses within their noise of each other but at values apart, the images
do not choose between those values. Pure numpy, so that the decisions are tested without a
renderer; engine/probes.py runs them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# Probes no shorter than this: Adam's first steps say little of where a start leads.
MIN_PROBE = 10
# Colours' extremes as shares of their range: near black and near white, where a start that
# the gradient cannot leave (a black lobe, a saturated one) is not yet stuck.
EXTREMES = (0.1, 0.9)
COLOURS = ("rgb", "texture")
# Values a share of this of their scale apart are different answers, where no interval says
# how far apart they may be (a probe's end has none of its own).
APART = 0.1
# Losses within this many standard errors of their difference tie.
TIE = 2.0
# Losses this share apart are equal: probes that render alike on the same seeds differ by
# rounding only.
ROUNDING = 1e-6
# A probe's ending loss is the mean of its last TAIL iterations (at least the loss's window).
TAIL = 5


@dataclass(frozen=True)
class Span:
    """What a start needs to know of a parameter: its kind, range, given start (flat) and
    channel count (a texture's; 0 otherwise)."""

    kind: str
    lo: float
    hi: float
    start: np.ndarray
    channels: int = 0

    @property
    def bounded(self) -> bool:
        return math.isfinite(self.lo) and math.isfinite(self.hi) and self.hi > self.lo


@dataclass
class Probe:
    """Where a probe began and ended: its start and its last values per parameter, its ending
    loss (the mean of its last iterations) and that mean's noise (a standard error), and how
    far each value would go at the pace of its last iterations in the job's iterations left
    (``reach``; a texture's or grid's by its mean level)."""

    index: int
    start: dict[str, np.ndarray] = field(default_factory=dict)
    values: dict[str, np.ndarray] = field(default_factory=dict)
    loss: float = math.inf
    noise: float = 0.0
    iterations: int = 0
    reach: dict[str, np.ndarray] = field(default_factory=dict)


def probe_length(iterations: int, starts: int) -> int:
    """Iterations per probe: max(MIN_PROBE, iterations / (4 starts)), fewer than the job's
    own, so that the best probe has iterations left to go on with (0: too short for any)."""
    return min(max(MIN_PROBE, iterations // (4 * starts)), iterations - 1)


def points(spans: dict[str, Span], n: int, seed: int) -> list[dict[str, np.ndarray]]:
    """Up to ``n`` distinct starts, the given one first: every bounded parameter at its
    range's middle; bounded colours at the EXTREMES of their range (the others at the
    middle); then points drawn uniformly from the ranges by ``seed`` (per channel for colours,
    one level for a texture's channel). Unbounded parameters keep their given start
    throughout, so a job with no bounded parameter has one start."""
    given = {k: np.asarray(s.start, dtype=np.float32) for k, s in spans.items()}
    candidates = [given, {k: _at(s, 0.5) for k, s in spans.items()}]
    for share in EXTREMES:
        candidates.append({k: _at(s, share if s.kind in COLOURS else 0.5)
                           for k, s in spans.items()})
    rng = np.random.default_rng(seed)
    out: list[dict[str, np.ndarray]] = []
    for _ in range(4 * n):  # draws that repeat a start are skipped, within reason
        if len(out) == n:
            break
        point = candidates.pop(0) if candidates else {
            k: _at(s, rng.uniform(size=_channels(s))) for k, s in spans.items()}
        if not any(_same(point, seen) for seen in out):
            out.append(point)
    return out


def _channels(s: Span) -> int:
    return 3 if s.kind == "rgb" else max(1, s.channels)


def _at(s: Span, share) -> np.ndarray:
    """The start ``share`` of the way through the range (per channel when an array), or the
    given start for a parameter without a finite range."""
    start = np.asarray(s.start, dtype=np.float32)
    if not s.bounded:
        return start
    level = np.float32(s.lo) + np.asarray(share, dtype=np.float32) * np.float32(s.hi - s.lo)
    if level.ndim == 0 or start.size % level.size:
        return np.full_like(start, float(np.mean(level)))
    return np.tile(level, start.size // level.size).astype(np.float32)


def _same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return all(np.allclose(a[k], b[k], rtol=1e-6, atol=1e-7) for k in a)


def reach(path: list[dict[str, np.ndarray]], left: int) -> dict[str, np.ndarray]:
    """How far each value (per component) would go in ``left`` iterations at the pace of
    the last TAIL of ``path`` (values per iteration)."""
    if len(path) < 2:
        return {}
    tail = path[-TAIL - 1:]
    pace = {k: np.abs(_level(tail[-1][k], False) - _level(tail[0][k], False)) / (len(tail) - 1)
            for k in tail[-1] if k in tail[0]}
    return {k: p * left for k, p in pace.items()}


def ending(losses: list[float], window: int) -> tuple[float, float]:
    """A probe's ending loss and its noise: the mean of its last max(TAIL, window) finite
    losses, and the standard error of that mean about their trend (a probe still descends,
    and its descent is not noise)."""
    tail = np.asarray([x for x in losses if math.isfinite(x)][-max(TAIL, window):], dtype=float)
    if tail.size == 0:
        return math.inf, 0.0
    mean = float(tail.mean())
    if tail.size < 3:
        return mean, 0.0
    t = np.arange(tail.size, dtype=float)
    residual = tail - np.polyval(np.polyfit(t, tail, 1), t)
    return mean, float(np.sqrt(np.sum(residual ** 2) / (tail.size - 2) / tail.size))


def best(probes: list[Probe]) -> Probe:
    """The probe the job goes on from: in order, a probe replaces the one held so far only
    with a loss lower beyond noise (not a ``_tie``), so that the given start is left only
    for a better one. A lower loss by chance is no reason to go elsewhere: three starts then
    end as one does where the images do not tell them apart. In order, so that the engine
    holds no more than the best so far and the probe running."""
    held = probes[0]
    for p in probes[1:]:
        if math.isfinite(p.loss) and (not math.isfinite(held.loss)
                                      or (p.loss < held.loss and not _tie(p, held))):
            held = p
    return held


def _tie(p: Probe, q: Probe) -> bool:
    """Whether two probes' losses are within TIE standard errors of their difference (never
    less than ROUNDING of the loss)."""
    allowed = TIE * math.hypot(p.noise, q.noise) + ROUNDING * abs(q.loss)
    return abs(p.loss - q.loss) <= allowed


def ties(probes: list[Probe]) -> list[Probe]:
    """The probes whose ending losses are within noise of the best one's: the best first.
    Noise is TIE standard errors of the difference, and never less than ROUNDING."""
    top = best(probes)
    return [top] + [p for p in probes
                    if p is not top and math.isfinite(p.loss) and _tie(p, top)]


def several(probes: list[Probe], spans: dict[str, Span],
            errors: dict[str, np.ndarray] | None = None, width: float = 4.0
            ) -> dict[str, list[list[tuple[float, float]]]]:
    """Per parameter and component, the answers the tied probes give where they differ:
    [(value, loss), ...] for each component on which a tied probe ends apart from the best
    one. Apart: outside ``width`` standard errors (``errors``, of the job's result, where
    finite), else more than APART of the component's scale (its range, or its magnitude
    where unbounded). Both must have settled: a value whose pace would take it that far in
    the job's iterations left (``Probe.reach``) was on its way, not at an answer (the loss
    of a probe still descending can tie by chance). Textures and grids are compared by their
    mean level."""
    tied = ties(probes)
    if len(tied) < 2:
        return {}
    errors = errors or {}
    out: dict[str, list[list[tuple[float, float]]]] = {}
    for key, span in spans.items():
        large = span.kind in ("texture", "volume_grid")
        ends = [_level(p.values[key], large) for p in tied if key in p.values]
        if len(ends) != len(tied):
            continue
        error = errors.get(key)
        components = []
        for c in range(ends[0].size):
            base = float(ends[0][c])
            scale = (span.hi - span.lo) if span.bounded else max(abs(base), 1e-6)
            allowed = APART * scale
            if (error is not None and not large and error.size == ends[0].size
                    and math.isfinite(float(error[c]))):
                allowed = width * float(error[c])
            values = [float(e[c]) for e in ends]
            reaches = [_component(p.reach.get(key), c) for p in tied]
            if any(abs(v - base) > max(allowed, r, reaches[0])
                   for v, r in zip(values[1:], reaches[1:])):
                components.append([(v, p.loss) for v, p in zip(values, tied)])
            else:
                components.append([])
        if any(components):
            out[key] = components
    return out


def _component(reached: np.ndarray | None, c: int) -> float:
    """A component's reach (0 where not recorded)."""
    return float(reached[c]) if reached is not None and c < np.size(reached) else 0.0


def _level(values: np.ndarray, large: bool) -> np.ndarray:
    flat = np.asarray(values, dtype=np.float64).ravel()
    return np.array([flat.mean()]) if large else flat


def reason(answers: list[tuple[float, float]]) -> str:
    """The verdict's words: 'the images allow several answers: 0.3 (loss 0.00121), ...'."""
    return "the images allow several answers: " + ", ".join(
        f"{v:.4g} (loss {loss:.4g})" for v, loss in answers)
