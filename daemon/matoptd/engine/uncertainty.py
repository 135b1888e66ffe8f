"""A standard error for each recovered value of a kept iteration: ``covariance.py``'s model,
fed from the job's own scene, references, loss and Adam state, with J from ``jacobian.py``.

Losses: each declares its model (losses.Loss): ``mse`` and ``dual_buffer`` are least squares
(dual_buffer's gradient averages two renders, halving the noise a step sees);
``multiscale_mse`` is least squares on an image pyramid, carried exactly by its (linear)
pyramid operator; ``brightness_independent_mse`` is least squares on images divided by their
means, linearized. ``mae`` is not least squares: its estimate is that of the least-squares fit
to one render (the L2 approximation), which a note says.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .. import engine_api as api
from ..range_notes import at_bound
from . import covariance
from .diagnosis import DECIDER, DECIDERS, Kept, widest
from .jacobian import (BUDGET, MAX_COMPONENTS, Clock, Job, Linearization, Pieces, Quantity,
                       Sensor, _Component, _latent_step, basis, drain, linearizing, quantity,
                       references)
from .losses import LOSSES
from .optimize import Best, Optimization, rate_share


@dataclass
class Adam:
    """Adam's state of one quantity (or gain) and the learning rate of each step taken."""

    second_moment: np.ndarray   # raw, flat, at its current level
    count: int
    rates: np.ndarray           # (steps,)
    gradients: np.ndarray | None = None  # (n, components) recorded, latent
    beta_1: float = covariance.BETA_1    # its first moment's decay (medium_damping lowers it)


@dataclass
class Estimate:
    errors: dict[str, api.StandardError]
    gains: dict[int, api.StandardError]
    notes: list[str]
    names: list[str] = field(default_factory=list)
    covariance: np.ndarray | None = None  # latent coordinates, per component of ``names``
    seconds: float = 0.0
    # for the diagnosis: the parameter keys (and "gain{sensor}") the estimate found trading
    # off, in pairs, and those it found not determined
    traded: set[frozenset[str]] = field(default_factory=set)
    undetermined: set[str] = field(default_factory=set)
    # notes about one parameter (its bound, its interval's width, a texture's mean level),
    # by key: engine/verdicts.py drops them where the diagnosis overrides the verdict
    about: dict[str, list[str]] = field(default_factory=dict)


def estimate(linearization: Linearization, quantities: list[Quantity],
             sensors: dict[int, Sensor], job: Job, adam: dict[str, Adam] | None) -> Estimate:
    """Standard errors of ``quantities`` and of the sensors' gains, from a linearization at
    (or near) their values. ``adam`` by quantity key ("gain{sensor}" for gains); None where
    the loss leaves Adam's model aside (mae)."""
    comps = linearization.components
    if linearization.fit is None:
        return Estimate({}, {}, [
            f"standard errors: not estimated for {len(comps)} components (more than "
            f"{MAX_COMPONENTS}): the Jacobian takes a render pass per component"])
    dynamics = None if adam is None else _dynamics(comps, quantities, adam)
    result = covariance.estimate(linearization.fit, dynamics)
    errors, gains, notes, about = _report(comps, quantities, sensors, result, job)
    owner = [c.key or f"gain{c.sensor}" for c in comps]
    index = {c.name: i for i, c in enumerate(comps)}
    traded = {frozenset((owner[index[a]], owner[index[b]]))
              for a, b, _ in covariance.correlated(result.noise, result.determined,
                                                   list(index))}
    return Estimate(errors, gains, notes, list(index), result.covariance,
                    linearization.seconds, {t for t in traded if len(t) == 2},
                    {owner[i] for i in np.flatnonzero(~result.determined)}, about)


def _dynamics(comps: list[_Component], quantities: list[Quantity], adam: dict[str, Adam]
              ) -> covariance.Dynamics | None:
    by_key = {q.key: q for q in quantities}
    steps = {len(a.rates) for a in adam.values()}
    if len(steps) != 1:
        return None
    n = steps.pop()
    rates = np.zeros((n, len(comps)))
    second = np.zeros(len(comps))
    measured = np.ones(len(comps), dtype=bool)
    recorded = max((len(a.gradients) for a in adam.values() if a.gradients is not None),
                   default=0)
    gradients = np.full((recorded, len(comps)), np.nan)
    count = max(a.count for a in adam.values())
    beta_1 = np.full(len(comps), covariance.BETA_1)
    for i, c in enumerate(comps):
        a = adam[c.key or f"gain{c.sensor}"]
        rates[:, i], beta_1[i] = a.rates, a.beta_1
        q = by_key.get(c.key)
        if q is not None and q.channels:
            # A mode of weights r_k (a mean level: all 1) moves by its texels' steps
            # projected on it: d = sum(r_k^2 d_k) / (sum r_k^2)^2 (a mean level's: mean(d_k) /
            # n), held as an equivalent second moment (Adam's v is the texels').
            v = a.second_moment.reshape(-1, q.channels)[:, c.index] / (1 - covariance.BETA_2
                                                                       ** max(a.count, 1))
            r2 = basis(q, c.mode).reshape(-1, q.channels)[:, c.index] ** 2
            per = np.sum(r2 / (np.sqrt(v) + covariance.EPSILON))
            level = (np.sum(r2) ** 2 / per) ** 2
            second[i] = level * (1 - covariance.BETA_2 ** max(count, 1))
            measured[i] = False
            continue
        second[i] = a.second_moment[c.index]
        if a.gradients is not None and len(a.gradients):
            gradients[-len(a.gradients):, i] = a.gradients[:, c.index]
    return covariance.Dynamics(rates, second, count, measured, gradients, beta_1)


def _report(comps: list[_Component], quantities: list[Quantity], sensors: dict[int, Sensor],
            result: covariance.Estimate, job: Job
            ) -> tuple[dict[str, api.StandardError], dict[int, api.StandardError], list[str],
                       dict[str, list[str]]]:
    """Standard errors on the value's scale (log ones by the delta method, v * se(log v)),
    how to read each component (and why one is not determined), the notes, and the notes
    about one parameter by its key. A component whose standard error spans more than a
    quarter of its range is not determined either: its interval would say nothing."""
    sd = np.sqrt(np.maximum(np.diag(result.covariance), 0))
    why = _reasons(comps, result)
    errors: dict[str, api.StandardError] = {}
    notes: list[str] = []
    about: dict[str, list[str]] = {}
    start = 0
    for q in quantities:
        n = len([c for c in comps if c.key == q.key])
        latent, ok = sd[start:start + n], result.determined[start:start + n]
        start += n
        if q.channels:  # its mean level per channel comes first; its smooth modes follow
            level = q.value.reshape(-1, q.channels).mean(axis=0)
            shown = np.where(ok[:q.channels], latent[:q.channels] * (level if q.log else 1.0),
                             np.inf)
            modes = n // q.channels - 1
            about.setdefault(q.key, []).append(
                f"{q.key}: its mean level is known to +- " + ", ".join(_short(shown)) +
                " (one standard error" + (" per channel" if q.channels > 1 else "") +
                (f", with {modes} smooth pattern(s) across it estimated beside it" if modes
                 else ", its texels' pattern held as recovered") +
                "); no standard error per texel: that would take a render pass per texel "
                f"({q.value.size // q.channels})")
            continue
        value = q.value.astype(np.float64)
        error = np.where(ok, latent * (value if q.log else 1.0), np.inf)
        reason = list(why[start - n:start])
        lower = max(q.lo, q.floor)
        bounded = math.isfinite(q.hi - q.lo) and (lower > 0 or not q.log)
        wide = ok & (error > widest(Kept(q.lo, q.hi, q.floor, q.log), value))
        for c in np.flatnonzero(wide):
            what = (f"more than a quarter of its range [{q.lo:g}, {q.hi:g}]"
                    if bounded else "more than a quarter of its value")
            about.setdefault(q.key, []).append(
                f"{_name(q, c)}: standard error {error[c]:.3g}, {what}: these images do not "
                f"decide it; what would: {DECIDER}")
            reason[c] = f"its standard error ({error[c]:.3g}) spans {what}"
        ok = ok & ~wide
        error = np.where(ok, error, np.inf)
        low = at_bound(value, lower) | ((q.floor > 0) & (value <= q.floor + 1e-6))
        high = at_bound(value, q.hi)
        reading = ["not_determined" if not d else "at_lower_bound" if lo else
                   "at_upper_bound" if hi else "two_sided" for d, lo, hi in zip(ok, low, high)]
        errors[q.key] = api.StandardError(error.astype(np.float32), reading,
                                          [r if not d else "" for r, d in zip(reason, ok)])
        for c in np.flatnonzero(ok & (low | high)):
            bound = lower if low[c] else q.hi
            where = "its floor" if low[c] and q.floor else "a bound"
            about.setdefault(q.key, []).append(
                f"{_name(q, c)}: ended at {where} {bound:g}, so its interval is one-sided: the "
                f"truth lies within {'+' if low[c] else '-'}{2 * error[c]:.3g} of it (two "
                "standard errors, on the side away from the bound)")
    gains: dict[int, api.StandardError] = {}
    for s, sensor in sensors.items():
        if sensor.gain is None:
            continue
        latent, ok = sd[start:start + 3], result.determined[start:start + 3]
        gains[s] = api.StandardError(
            np.where(ok, latent * sensor.gain, np.inf).astype(np.float32),
            ["two_sided" if d else "not_determined" for d in ok],
            [r if not d else "" for r, d in zip(why[start:start + 3], ok)])
        start += 3
    for group in result.groups:
        names = [comps[k].name for k in group]
        if len(names) == 1:
            notes.append(f"{names[0]}: not determined by these images (the render does not "
                         f"change with it); what would decide it: {DECIDER}")
        else:
            notes.append(f"not determined by these images: {', '.join(names)} change the "
                         "render as one (J^T J is singular in a direction that mixes them), "
                         f"so only a combination of them is decided; what would decide them: "
                         f"{DECIDERS}")
    noisy = [c.name for c, n in zip(comps, result.noisy) if n]
    if noisy:
        notes.append(f"no standard error for {', '.join(noisy)}: the derivative of the images "
                     "was too noisy to estimate in the time the estimate may take (the other "
                     "standard errors hold them at their values)")
    for a, b, r in covariance.correlated(result.noise, result.determined,
                                         [c.name for c in comps]):
        how = "rises as the other falls" if r < 0 else "moves with the other"
        notes.append(f"{a} and {b} trade off (correlation {r:+.2f} of their estimates: one "
                     f"{how} at nearly the same loss), so the images decide their combination "
                     "better than either")
    if not LOSSES[job.loss].least_squares:
        notes.append("standard errors are those of a least-squares fit to one render (the "
                     f"L2 approximation): {job.loss} is not least squares, and how far Adam's "
                     "last steps scatter is not modelled for it")
    return errors, gains, notes, about


def _reasons(comps: list[_Component], result: covariance.Estimate) -> list[str]:
    """Why each component the estimate leaves undetermined is, in a few words ("" for the
    determined ones)."""
    why = ["" if d else "it lies in a direction these images do not resolve"
           for d in result.determined]
    for group in result.groups:
        for k in group:
            others = [comps[o].name for o in group if o != k]
            why[k] = (f"it changes the render as {', '.join(others)} "
                      f"{'does' if len(others) == 1 else 'do'}" if others
                      else "the render does not change with it")
    for k in np.flatnonzero(result.noisy):
        why[k] = "its derivative was too noisy to estimate in the time allowed"
    return why


def _name(q: Quantity, c: int) -> str:
    return q.key if q.value.size == 1 else f"{q.key}[{c}]"


def _short(v: np.ndarray) -> list[str]:
    return [f"{x:.3g}" if np.isfinite(x) else "not determined" for x in np.ravel(v)]


def of_kept(opt: Optimization, chosen: list[tuple[str, Best]], kinds: dict[str, str],
            shapes: dict[str, list[int]]) -> dict[str, Estimate]:
    """``estimating`` in one go."""
    return drain(estimating(opt, chosen, kinds, shapes))


def estimating(opt: Optimization, chosen: list[tuple[str, Best]], kinds: dict[str, str],
               shapes: dict[str, list[int]]) -> Pieces[dict[str, Estimate]]:
    """Estimates for a job's kept iterations (best, last), read from its Optimization
    (``kinds`` and ``shapes`` of its parameters), in pieces of one pass of J each: a job's
    end runs them as turns of its worker, other jobs' iterations between them. An estimate
    that fails leaves the results as they are, with a note saying why."""
    try:
        return (yield from _of_kept(opt, chosen, kinds, shapes))
    except Exception as exc:  # noqa: BLE001 - the job's results stand without them
        while exc.__cause__ is not None:  # Dr.Jit's says "see above": the cause says what
            exc = exc.__cause__
        note = f"standard errors: not estimated ({type(exc).__name__}: {exc})"
        return {which: Estimate({}, {}, [note]) for which, _ in chosen}


def _of_kept(opt: Optimization, chosen: list[tuple[str, Best]], kinds: dict[str, str],
             shapes: dict[str, list[int]]) -> Pieces[dict[str, Estimate]]:
    """The images are linearized at the last iteration, and again at the best only when it
    lies further from it than two difference steps (over which J is taken as constant
    anyway) and the first kept within its share of the time J may take."""
    kept = []
    gained = {r.sensor for r in opt.records.values() if r.is_gain}
    for which, it in sorted(chosen, key=lambda c: c[0] != "last"):
        quantities, skipped = _quantities(opt, it, kinds, shapes)
        sensors = references(opt.renders.references,
                             {s: g for s, g in it.gains.items() if s in gained})
        kept.append((which, it, quantities, sensors, skipped))
    apart = [k for k in kept[1:] if not _near(k[2], kept[0][2])] if kept else []
    job = Job(opt.settings.loss, opt.spp, opt.settings.seed, opt.settings.clamp,
              opt.progress.elapsed / (1 + len(apart)))
    out: dict[str, Estimate] = {}
    linearized: Linearization | None = None
    clock = Clock()
    count, reused = 0, ""
    freeze = any(c.name == "frozen" for c in opt.active)  # --choice frozen=off: unfrozen
    notes: list[str] = []
    for which, it, quantities, sensors, skipped in kept:
        if linearized is None or any(which == k[0] for k in apart):
            # A second linearization only where the first left it its share of the budget:
            # at the least spp a small image's J costs its passes' tracing, whatever the spp.
            if linearized is not None and linearized.seconds > BUDGET * job.seconds:
                reused = (f"; {which}'s from the linearization at {kept[0][0]}, since a "
                          "second would pass the time standard errors may take")
            else:
                with opt.renders.holding(it.values):
                    linearized = yield from linearizing(
                        opt.renders.scene, opt.renders.params, opt.renders.integrator,
                        opt.integrator_name, quantities, sensors, job, freeze, clock=clock)
                count += 1
                notes += linearized.notes
        adam = _adam(opt, it) if LOSSES[job.loss].least_squares else None
        out[which] = estimate(linearized, quantities, sensors, job, adam)
        out[which].notes[:0] = skipped
    seconds = clock()
    for e in out.values():
        e.seconds = seconds
        if e.names:
            e.notes.append(f"standard errors: {len(e.names)} components, {seconds:.2g} s "
                           f"({100 * seconds / max(opt.progress.elapsed, 1e-9):.0f}% of the job's "
                           f"optimizing time{', two linearizations' if count > 1 else ''}"
                           f"{reused})")
            e.notes += list(dict.fromkeys(notes))
    return out


def _quantities(opt: Optimization, kept: Best, kinds: dict[str, str],
                shapes: dict[str, list[int]]) -> tuple[list[Quantity], list[str]]:
    out, skipped = [], []
    for key, k in opt.kept.items():
        value = np.asarray(kept.values[key], dtype=np.float64)
        summarized = kinds.get(key) in ("texture", "volume_grid")
        if value.size > api.SMALL and not summarized:
            skipped.append(f"{key}: no standard error ({value.size} components; only scalars, "
                           "colours, textures and grids are estimated)")
            continue
        out.append(quantity(key, value, k, max(opt.records[key].channels, 1) if summarized
                            else 0, tuple(shapes.get(key, ())) if summarized else ()))
    return out, skipped


def _adam(opt: Optimization, kept: Best) -> dict[str, Adam]:
    """Adam's state now, and the learning rate of each step that led to ``kept``."""
    c = opt.settings
    sensors = len(opt.renders.references)
    per = sensors if c.sensor_mode == "step_per_sensor" and sensors > 1 else 1
    out = {}
    for key, r in opt.records.items():
        _, _, _, (t, _, v, _) = opt.opt.state[key]
        rate, recorded = r.step_rate, r.gradients
        held = set(r.held)  # a held step moved nothing
        factors = np.repeat([0.0 if i in held else rate_share(c, i, r)
                             for i in range(max(kept.iteration, 0))], per)
        out[key] = Adam(np.asarray(v, dtype=np.float64).ravel(),
                        int(np.asarray(t).ravel()[0]), rate * factors,
                        np.array([np.ravel(g) for g in recorded]) if recorded else None,
                        opt.opt.beta_1)
    return out


def _near(quantities: list[Quantity], others: list[Quantity]) -> bool:
    """Whether every value lies within two difference steps (latent) of the other's."""
    for q, o in zip(quantities, others):
        u, w = ((np.log(np.maximum(x.value, 1e-30)) if q.log else x.value) for x in (q, o))
        if np.any(np.abs(u - w) > 2 * _latent_step(q)):
            return False
    return True
