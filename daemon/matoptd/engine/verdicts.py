"""One verdict per recovered component, from the two things that judge it: the standard error
(uncertainty.py, from the images linearized at the kept iteration) and the diagnosis
(diagnosis.py, from the job's history). They look at different evidence and can disagree:
a drift on gradients of no consistent sign, or two parameters wandering in step at a level
loss, say the images do not decide a value that a local fit still pins to +- a little. The
verdict takes the more cautious: where either finds a component not decided, it is not
determined (standard error +inf, with the reason), and the notes that gave it an interval
go. Every surface (status, result, export, the clients) shows what this returns.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .. import engine_api as api
from .diagnosis import Diagnosis

if TYPE_CHECKING:  # uncertainty loads Mitsuba's integrators, which need a variant set
    from .uncertainty import Estimate


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

    A drift on noise is the one finding an interval can answer: a value that wandered by no
    more than two standard errors did what its interval says it may (the note says so
    instead); one that wandered further is not determined."""
    errors = dict(estimate.errors)
    about = {key: list(notes) for key, notes in estimate.about.items()}
    replaced: dict[str, str] = {}
    for key, why in diagnosed.undecided.items():
        had = errors.get(key)
        if key in diagnosed.drifts and had is not None:
            moved, note = diagnosed.drifts[key]
            finite = np.isfinite(had.error)
            if finite.all() and np.all(moved <= 2 * had.error):
                replaced[note] = (f"{key} drifted by "
                                  f"{_short(moved)} over its last iterations on gradients of "
                                  "no consistent sign: within two standard errors, the "
                                  "scatter its interval allows")
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
    notes = ([replaced.get(n, n) for n in diagnosed.notes]
             + [note for key in about for note in about[key]] + list(estimate.notes))
    return Verdicts(errors, dict(estimate.gains), notes)


def _short(v: np.ndarray) -> str:
    return ", ".join(f"{x:.3g}" for x in np.ravel(v))
