"""Starts compared: a job with JobSettings.starts > 1 runs short probes from diverse starts
(starts.py says where) before its first checkpoint, and goes on from the best one.

Each probe is the job's own loop (optimize.Optimization) from its start, run for
``starts.probe_length`` iterations on the same seeds, so that probes which render alike end
at the same loss. The best probe is kept as it stands, Adam's moments and schedule with it:
its iterations are the job's first ones, and the job runs on from there. The others' time
goes on the job's clock. The probes' ends travel in the progress (and so in checkpoints), for
the verdicts at the end (verdicts.several).
"""

from __future__ import annotations

import gc
from typing import Callable

import numpy as np

from .. import engine_api as api
from . import starts
from .optimize import Optimization
from .records import Step


def iteration_record(opt: Optimization, s: Step, seconds: float | None = None
                     ) -> api.IterationRecord:
    """What the daemon records of an iteration (small values only); ``seconds``: the job's
    optimizing time then, if not the run's own."""
    return api.IterationRecord(
        s.iteration, opt.progress.elapsed if seconds is None else seconds, s.loss,
        {k: v for k, v in s.values.items() if v.size <= api.SMALL},
        s.errors, s.image_error, s.gains, s.spp)


def spans(opt: Optimization) -> dict[str, starts.Span]:
    return {k: starts.Span(r.kind, r.lo, r.hi, r.start, r.channels)
            for k, r in opt.parameters.items()}


def run(make: Callable[[dict[str, np.ndarray]], Optimization], notes: list[str]
        ) -> tuple[Optimization, list[api.IterationRecord]]:
    """The probes: ``make`` builds the job's loop from a start (values by key; {}: the given
    start), each runs ``probe_length`` iterations. Returns the best probe's loop, ready to go
    on, and its iterations' records; says in ``notes`` what each probe did ("probe k of N:
    ..."). At most two loops are held at once: the best so far and the one running."""
    opt = make({})
    settings = opt.settings
    found = spans(opt)
    where = starts.points(found, settings.starts, settings.seed)
    length = starts.probe_length(settings.iterations, len(where))
    if len(where) < 2 or length < 1:
        notes.append(f"starts: one start only ({settings.starts} asked): "
                     + ("no parameter has a bounded range to start elsewhere in"
                        if len(where) < 2 else f"{settings.iterations} iteration(s) leave "
                        "no room for probes"))
        return opt, []
    initial = opt.initial
    large = {k for k, s in found.items() if s.kind in ("texture", "volume_grid")}
    kept: tuple[Optimization, list[api.IterationRecord]] | None = None
    probes: list[starts.Probe] = []
    spent = 0.0  # the probes' time before this one
    for index, point in enumerate(where):
        if index:  # the first is the given start, built above
            opt = make(point)
        rows, losses, path = [], [], []
        for _ in range(length):
            s = opt.step()
            rows.append(iteration_record(opt, s, spent + opt.progress.elapsed))
            losses.append(s.loss)
            # a large value by its mean level: the tail's move is all that is kept of it
            path = (path + [{k: v if k not in large else np.mean(v, keepdims=True)
                             for k, v in s.values.items()}])[-starts.TAIL - 1:]
            if s.done:
                break
        loss, noise = starts.ending(losses, opt.loss.window)
        probe = starts.Probe(index, point, dict(opt.progress.last.values), loss, noise,
                             len(rows), starts.reach(path, settings.iterations - len(rows)))
        probes.append(probe)
        spent += opt.progress.elapsed
        notes.append(f"probe {index + 1} of {len(where)}: from {_values(point, found)}, "
                     f"{len(rows)} iterations to {_values(probe.values, found)}, "
                     f"loss {loss:.4g} +- {noise:.2g}")
        if kept is None or starts.best(probes) is probe:
            kept = (opt, rows)
        opt = None
        gc.collect()  # a losing probe's buffers go before the next one is built
    opt, rows = kept
    chosen = starts.best(probes)
    opt.progress.probes = probes
    # The job's clock takes the whole start, the probes and their loading in it (service).
    opt.progress.elapsed = 0.0
    opt.initial = initial  # the job's given start, as a resume from a checkpoint sees it
    opt._apply()  # the scene holds the last probe's values
    notes.append(f"starts: {len(where)} compared over {length} iterations each; the job "
                 f"goes on from probe {chosen.index + 1} ("
                 + ("the given start: none ended lower beyond noise)" if chosen.index == 0
                    else "its loss lower beyond noise)"))
    return opt, rows


def _values(point: dict[str, np.ndarray], found: dict[str, starts.Span]) -> str:
    """A start or an end in a few words: small values as numbers, large ones by mean."""
    words = []
    for key, v in point.items():
        flat = np.asarray(v).ravel()
        shown = (", ".join(f"{x:.3g}" for x in flat) if flat.size <= 3
                 else f"mean {float(flat.mean()):.3g}")
        words.append(f"{key} = {shown}" if len(found) > 1 else shown)
    return "; ".join(words)
