"""One verdict per recovered component, from the two things that judge it: the standard error
(uncertainty.py, from the images linearized at the kept iteration) and the diagnosis
(diagnosis.py, from the job's history). They look at different evidence and can disagree:
a drift on gradients of no consistent sign, or two parameters wandering in step at a level
loss, say the images do not decide a value that a local fit still pins to +- a little. The
verdict takes the more cautious: a wander widens the interval to span it; where either finds a
component not decided otherwise, or the widened interval says nothing, it is not determined
(standard error +inf, with the reason), and the notes that gave it an interval go. Every
surface (status, result, export, the clients) shows what this returns.

A job that compared starts (JobSettings.starts) adds what no standard error can know: other
basins. Where its probes ended at losses within noise of the best one's but at values outside
each other's intervals, the component is not determined, its reason listing the answers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .. import engine_api as api
from . import starts
from .diagnosis import Diagnosis, Wander

if TYPE_CHECKING:  # uncertainty loads Mitsuba's integrators, which need a variant set
    from .uncertainty import Estimate


# An interval's width in standard errors (value +- 2). A value that wandered on noise further
# than that gets a standard error of its wander over WIDTH: its interval then spans the wander.
# The local fit gives the images' noise; the wander adds the scatter of the steps that end on it
# (at 60 iterations and 32 px, half the roughnesses and sigma_ts of the calibration cases wandered
# past their local intervals while ending within 3% of the truth).
WIDTH = 4.0


@dataclass
class Verdicts:
    """A kept iteration's verdicts: per value and per gain, and the notes that go with them
    (the diagnosis's first)."""

    errors: dict[str, api.StandardError]
    gains: dict[int, api.StandardError]
    notes: list[str]


def reconcile(estimate: Estimate, diagnosed: Diagnosis, sizes: dict[str, int]) -> Verdicts:
    """The estimate's verdicts, with the parameters the diagnosis finds undecided made not
    determined. ``sizes``: the component count of each value a result shows inline, so that
    an undecided one gets its verdict even where no standard error was estimated.

    A finding from wandering (a drift on noise, two parameters in step at a level loss) is
    the one an interval can answer: each value's interval is widened to span its wander (the
    note says so instead); where that would make one of them too wide to say anything
    (diagnosis.widest), or one has no interval, they are not determined."""
    errors = dict(estimate.errors)
    about = {key: list(notes) for key, notes in estimate.about.items()}
    widened = {key: _widened(errors.get(key), w) for key, w in diagnosed.wander.items()}
    answered = {w.note: w.within for w in diagnosed.wander.values()
                if all(widened[k] is not None for k, o in diagnosed.wander.items()
                       if o.note == w.note)}
    for key, why in diagnosed.undecided.items():
        had = errors.get(key)
        if key in diagnosed.wander and diagnosed.wander[key].note in answered:
            if not np.array_equal(widened[key].error, had.error):
                errors[key] = widened[key]
                about[key] = [n for n in about.get(key, []) if "one-sided" not in n]
            continue
        if had is None and key not in sizes:
            about.pop(key, None)  # a texture or grid: its mean level's note said +- too
            continue
        n = len(had.reading) if had is not None else sizes[key]
        # a component the estimate left undetermined keeps its own reason
        kept = ([r if d == "not_determined" and r else why
                 for d, r in zip(had.reading, had.reason or [""] * n)]
                if had is not None else [why] * n)
        errors[key] = api.StandardError(np.full(n, np.inf, dtype=np.float32),
                                        ["not_determined"] * n, kept)
        about.pop(key, None)  # an interval or a bound's one-sided interval it no longer has
    notes = ([answered.get(n, n) for n in diagnosed.notes]
             + [note for key in about for note in about[key]] + list(estimate.notes))
    return Verdicts(errors, dict(estimate.gains), notes)


def _widened(verdict: api.StandardError | None, wander: Wander) -> api.StandardError | None:
    """The verdict with each standard error at least the wander over WIDTH; None where it has
    no finite interval to widen, or the widened one passes ``wander.limit``."""
    if verdict is None or not np.isfinite(verdict.error).all():
        return None
    error = np.maximum(np.asarray(verdict.error, dtype=np.float64), wander.moved / WIDTH)
    if np.any(error > wander.limit):
        return None
    return api.StandardError(error.astype(np.float32), list(verdict.reading),
                             list(verdict.reason))


def several(said: Verdicts, probes: list[starts.Probe], spans: dict[str, starts.Span]
            ) -> Verdicts:
    """The verdicts with every component on which the probes found several answers not
    determined, the reason listing each answer and its probe's loss. A value without
    per-component verdicts (a texture, a grid) gets a note instead."""
    if len(probes) < 2:
        return said
    widths = {k: np.asarray(e.error, dtype=np.float64) for k, e in said.errors.items()}
    errors, notes = dict(said.errors), list(said.notes)
    for key, components in starts.several(probes, spans, widths, WIDTH).items():
        had = errors.get(key)
        if had is None or len(had.reading) != len(components):
            notes += [f"{key}: {starts.reason(a)}" for a in components if a]
            continue
        error, reading = np.array(had.error, dtype=np.float32), list(had.reading)
        reason = list(had.reason) or [""] * len(reading)
        for c, answers in enumerate(components):
            if answers:
                error[c], reading[c], reason[c] = np.inf, "not_determined", starts.reason(answers)
        errors[key] = api.StandardError(error, reading, reason)
    return Verdicts(errors, said.gains, notes)
