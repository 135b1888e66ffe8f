"""J, the derivative of each rendered pixel with respect to each component of a kept
iteration (in the latent coordinates Adam steps on), with the render noise and residual it is
read against: what ``uncertainty.py`` turns into standard errors (the algebra is in
``covariance.py``).

J comes one pass per component (a colour's three in one pass where the render keeps channels
apart: ``_passes``): Mitsuba's forward mode (``render_forward``) where the integrator has it,
else a central difference of two renders with the same samples. prbvolpath has no forward
mode; a dielectric's eta is differenced always: near the specular limit prb's derivative
misses where the refracted rays go, and elsewhere it agrees with the difference but is far
noisier (a rough glass ball at 64 spp: J^T J to within 67% against 10%). Each column is
estimated twice from independent samples, and only products across the two enter J^T J, so
J's own noise does not inflate it; with prb, prb_basic and prbvolpath both estimates come from
one pass at twice the samples, and every forward pass of a round replays one primal pass
(split_samples.py). A column whose J^T J its noise still swamps gets more samples
(``linearize``). A gain's column is the gained render's channel itself. A texture or grid
enters as its low-frequency modes per channel (``MODES``): its mean level (every texel moved
together: what trades against a scalar, a medium's albedo grid against its sigma_t) and a
left-right and a top-bottom ramp across it (a brighter left half can stand in for a light
or a roughness that shifts light across the image). Held at its recovered pattern, a texture
that could explain the image in a scalar's place would not widen that scalar's interval. A
standard error per texel would take one pass per texel.

The render noise (S_r) and the residual of the mean render (S_R: the reference's own noise
and what the scene does not model) come from two more renders A, B at the job's spp:
(A - B)^2 / 2 and (A - R)(B - R) per pixel-channel, both unbiased; the second, far the
noisier, is pooled over the image unless it shows a misfit (covariance.residual_noise). The
loss decides how the rows are weighed and what noise a step sees (losses.Loss).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Generator, TypeVar

import drjit as dr
import mitsuba as mi
import numpy as np

from . import covariance, frozen, parameters, split_samples
from .diagnosis import Kept
from .renders import Reference
from .rows import linearized, rows


FORWARD_MODE = ("prb", "prb_projective", "direct_projective")  # integrators with render_forward


MAX_COMPONENTS = 48   # "a few dozen": J costs a pass per component


# A texture's or grid's directions in J, per channel: its mean level, then ramps from -1 to 1
# along its width and its height (axes -2 and -3 of a (..., H, W, C) tensor). The ramps go
# only when the components pass MAX_COMPONENTS: dropped for time, they would leave a scalar
# the narrower interval of a texture held at its pattern (their passes may pass the budget).
MODES = ("mean level", "left-right ramp", "top-bottom ramp")


BUDGET = 0.1          # of the job's optimizing time, for all of J (its spp follows, down to 1)


# ... but at least the time of FLOOR of the job's renders, up to FLOOR_SHARE of the job: a
# tenth of a short job of small frozen iterations (a few seconds at 32 px) left half the
# calibration cases' sigma_t and roughness "too noisy to estimate in the time allowed".
FLOOR, FLOOR_SHARE = 32, 0.25


# ... and at least this many seconds, whatever the job's: a job of small frozen iterations
# on a fast machine takes well under a second (the textured calibration case: 0.4 s), whose
# quarter left 15 of 40 roughnesses "too noisy" (1 with this floor; 1 of 60 on a slower CPU).
FLOOR_SECONDS = 1.0


# ... and at most this many seconds: the end of a job runs under the daemon's watchdog (5x its
# base of 120 s), which an hours-long job's 10% would pass.
BUDGET_CAP = 60.0


SIGNAL = 8.0          # J^T J's diagonal over its noise that a component's J should reach


MAX_SAMPLES = 64      # times the job's spp: the most samples one component's J gets


# Central-difference steps in latent coordinates: large enough that the paths a step
# switches (a free flight crossing the surface) do not swamp the difference with noise
# (sigma_t's J^T J at 2% varied 100% between estimates, at 5% 6%), small enough to stay a
# slope (a secant over +-10% of a smooth curve differs from its slope by ~0.2%).
LOG_STEP = 0.1


LINEAR_STEP = 0.05    # of the range (of the value's size when the range is unbounded)


# A dielectric's eta: 4% near 1.5. Over a rough interface a difference's noise is mostly the
# lanes whose reflect/refract choice the step flips (variance ~ step, signal^2 ~ step^2): at
# 0.03, 3 of 20 rough glass balls (60 iterations) were left without a standard error, at 0.06 1.
ETA_STEP = 0.06


DRAW = 0x5EED0E55     # samples of their own, apart from any iteration's


@dataclass
class Quantity:
    """One optimized parameter as the estimate sees it."""

    key: str
    value: np.ndarray      # flat, as the kept iteration shows it
    log: bool              # optimized as u = log v
    lo: float              # the range it is kept in (a width's floor applied when log)
    hi: float
    floor: float = 0.0     # the least value it is shown at (a principled roughness)
    channels: int = 0      # > 0: a texture or grid, estimated by its MODES per channel
    difference: bool = False  # J by a central difference (a dielectric's eta)
    eta: bool = False      # a dielectric's eta (its difference step)
    shape: tuple[int, ...] = ()  # a texture's or grid's, channels last (() : mean level only)


@dataclass
class Sensor:
    """A sensor's reference as the loss sees it."""

    reference: np.ndarray          # (H, W, 3)
    weight: np.ndarray | None      # (H, W, 3) mask weight, None: every pixel counts
    gain: np.ndarray | None = None  # RGB exposure gain (fit_exposure), optimized in log
    name: str = ""


@dataclass
class Job:
    """What the estimate needs from the job besides its values."""

    loss: str
    spp: int
    seed: int
    clamp: bool
    seconds: float              # its optimizing time so far (J may take BUDGET of it)


def quantity(key: str, value: np.ndarray, kept: Kept, channels: int = 0,
             shape: tuple[int, ...] = ()) -> Quantity:
    """A parameter as J sees it, at ``value``, in the coordinates it is stepped in."""
    eta = parameters.dielectric_eta(key)  # the log_space choice's kept range is v's
    return Quantity(key, value, kept.log, kept.lo, kept.hi, kept.floor, channels, eta, eta,
                    shape)


def references(refs: dict[int, Reference], gains: dict[int, np.ndarray]
               ) -> dict[int, Sensor]:
    """The references as J reads them, with the exposure gain of each gained sensor."""
    return {s: Sensor(np.asarray(ref.image), None if ref.weight is None
                      else np.asarray(ref.weight), gains.get(s), ref.name)
            for s, ref in refs.items()}


@dataclass
class _Component:
    name: str       # for notes: "key", "key[1]", "key (mean level, channel 0)", "gain of x[2]"
    key: str        # the quantity's key, or "" for a gain
    index: int      # component of the value, or channel of a level or a gain
    sensor: int = -1  # for a gain
    mode: int = 0   # of a texture or grid: which of MODES


def modes(q: Quantity) -> list[int]:
    """The MODES a texture or grid enters J by: its mean level, and a ramp along each of
    its width and height that is longer than one texel."""
    if len(q.shape) < 3 or int(np.prod(q.shape)) != q.value.size:
        return [0]
    return [0] + [m for m, axis in ((1, -2), (2, -3)) if q.shape[axis] > 1]


def basis(q: Quantity, mode: int) -> np.ndarray:
    """The flat weight of each element of ``q`` in a mode (every channel alike)."""
    if mode == 0:
        return np.ones(q.value.size)
    axis = -2 if mode == 1 else -3
    ramp = np.linspace(-1.0, 1.0, q.shape[axis])
    shape = [1] * len(q.shape)
    shape[axis] = q.shape[axis]
    return np.broadcast_to(ramp.reshape(shape), q.shape).ravel()


def components(quantities: list[Quantity], sensors: dict[int, Sensor], smooth: bool = True
               ) -> list[_Component]:
    """Each quantity's components (a texture's or grid's MODES per channel, mean levels
    first, the ramps only with ``smooth``), then each gain's."""
    out = []
    for q in quantities:
        if q.channels:
            for m in modes(q) if smooth else [0]:
                out += [_Component(f"{q.key} ({MODES[m]}" + (f", channel {c})" if q.channels > 1
                                                             else ")"), q.key, c, mode=m)
                        for c in range(q.channels)]
        else:
            out += [_Component(q.key if q.value.size == 1 else f"{q.key}[{c}]", q.key, c)
                    for c in range(q.value.size)]
    for s, sensor in sensors.items():
        if sensor.gain is not None:
            out += [_Component(f"gain of {sensor.name or f'sensor {s}'}[{c}]", "", c, s)
                    for c in range(3)]
    return out


@dataclass
class Linearization:
    """A kept iteration's images linearized (covariance.Linearized), with its components."""

    components: list[_Component]
    fit: covariance.Linearized | None  # None: too many components to estimate
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)  # for the job's notes: frozen or why not


T = TypeVar("T")
Pieces = Generator[None, None, T]  # work that yields between its pieces, then returns a T


class Clock:
    """The seconds an estimate in pieces has run, without the pauses between them (other
    jobs' turns on the worker): its budget is of its own time."""

    def __init__(self) -> None:
        self.spent, self.since = 0.0, time.perf_counter()

    def __call__(self) -> float:
        return self.spent + time.perf_counter() - self.since

    def piece(self) -> Pieces[None]:
        """A piece ends here: the clock stops until the next begins."""
        self.spent = self()
        yield
        self.since = time.perf_counter()


def drain(pieces: Pieces[T]) -> T:
    """Work in pieces done in one go: its value."""
    while True:
        try:
            next(pieces)
        except StopIteration as done:
            return done.value


def linearize(scene: mi.Scene, params: mi.SceneParameters, integrator: mi.Integrator,
              integrator_name: str, quantities: list[Quantity], sensors: dict[int, Sensor],
              job: Job, freeze: bool = False, fixed: bool = False) -> Linearization:
    """``linearizing`` in one go."""
    return drain(linearizing(scene, params, integrator, integrator_name, quantities, sensors,
                             job, freeze, fixed))


def linearizing(scene: mi.Scene, params: mi.SceneParameters, integrator: mi.Integrator,
                integrator_name: str, quantities: list[Quantity], sensors: dict[int, Sensor],
                job: Job, freeze: bool = False, fixed: bool = False,
                clock: Clock | None = None) -> Pieces[Linearization]:
    """``_linearize`` with its passes frozen (split_samples.Frozen) where ``freeze`` and the
    integrator allows, else unfrozen; a frozen estimate that fails is made again unfrozen,
    its notes saying why. ``fixed``: as ``_linearize``'s. It yields after each pass: the
    daemon runs other jobs between its pieces."""
    clock = clock or Clock()
    why = unfrozen(integrator, integrator_name) if freeze else ""
    if not freeze or why:
        out = yield from _linearize(scene, params, integrator, integrator_name, quantities,
                                    sensors, job, clock, fixed=fixed)
        out.notes += [f"standard errors: J's passes not frozen: {why}"] if why else []
        return out
    try:
        out = yield from _linearize(scene, params, integrator, integrator_name, quantities,
                                    sensors, job, clock, split_samples.Frozen(), fixed)
    except Exception as exc:  # noqa: BLE001 - the unfrozen passes give the same estimate
        while exc.__cause__ is not None:  # Dr.Jit's says "see above": the cause says what
            exc = exc.__cause__
        for q in quantities:  # a pass may have failed with its leaves or sides set
            params[q.key] = parameters.assign(params[q.key], q.value)
        params.update()
        out = yield from _linearize(scene, params, integrator, integrator_name, quantities,
                                    sensors, job, clock, fixed=fixed)
        out.notes.append(f"standard errors: J's passes not frozen: recording them failed "
                         f"({type(exc).__name__}: {exc})")
    return out


def unfrozen(integrator: mi.Integrator, integrator_name: str) -> str:
    """Why J's passes cannot be frozen with this integrator, in words; "" when they can."""
    if integrator_name not in frozen.FREEZABLE:
        return (f"the integrator {integrator_name} samples silhouette edges into arrays of "
                "data-dependent size, which a recording cannot replay")
    if not split_samples.shares_primal(integrator):
        return f"the integrator {integrator_name}'s forward mode is not RBIntegrator's"
    return ""


def _linearize(scene: mi.Scene, params: mi.SceneParameters, integrator: mi.Integrator,
               integrator_name: str, quantities: list[Quantity], sensors: dict[int, Sensor],
               job: Job, clock: Clock, recorded: split_samples.Frozen | None = None,
               fixed: bool = False) -> Pieces[Linearization]:
    """J, the render noise and the residual at the values ``params`` holds (set by the
    caller to ``quantities``' values), as H, Q and Q_R.

    ``fixed``: J at the job's spp in one round, whatever the time (a step taken from it must
    be the same on any machine, and after a checkpoint).

    J is first estimated at the spp that half the budget allows (_samples); a component
    whose J^T J is then less than SIGNAL times its own noise gets more samples, four times as
    many a round, while the whole fits in the budget: a derivative image can be far
    noisier than its render (a glass ball's eta at 16 spp: noise ten times the signal), and a
    standard error from a J^T J that noise swamps would be noise too."""
    began = clock()
    comps = components(quantities, sensors)
    if len(comps) > MAX_COMPONENTS:
        comps = components(quantities, sensors, smooth=False)
    if len(comps) > MAX_COMPONENTS:
        return Linearization(comps, None)
    by_key = {q.key: q for q in quantities}
    # unfrozen, as the spp the passes get follows their cost at 1 spp and at the job's: a
    # frozen pass costs less, which the rounds' own times then show
    renders = {s: [_render(scene, params, integrator, s, job.spp, _draw(job.seed, n))
                   for n in (0, 1)] for s in sensors}
    full = (clock() - began) / (2 * len(sensors))
    began_one = clock()
    if not fixed:
        _render(scene, params, integrator, next(iter(sensors)), 1, _draw(job.seed, 9))
    one = clock() - began_one
    budget = min(max(BUDGET * job.seconds, FLOOR_SECONDS,
                     min(FLOOR * full * len(sensors), FLOOR_SHARE * job.seconds)), BUDGET_CAP)
    split = split_samples.shares_primal(integrator)

    def render(s: int) -> float:  # its time at 1 spp plus a share of the rest by its spp
        return one + max(full - one, 0) * (s - 1) / max(job.spp - 1, 1)

    def cost(s: int) -> float:  # of a pass's two estimates at s spp each
        # split: one forward pass at 2s (its primal shared), about two renders' work;
        # else two estimates of a primal and a forward pass (or two sides) each
        return 2 * render(2 * s) if split else 4 * render(s)

    count = len(sensors) * len(_passes([k for k, c in enumerate(comps) if c.key],
                                       comps, by_key, params))
    spp = job.spp if fixed else _samples(budget / 2 - (clock() - began), count,
                                         cost, job.spp)
    # columns[sensor][n][k]: estimate n (of two) of component k's column, over samples[k]
    columns = {s: [[None] * len(comps) for _ in (0, 1)] for s in sensors}
    samples = np.zeros(len(comps))
    todo = [k for k, c in enumerate(comps) if c.key]
    together = [q for q in quantities if forward_mode(q, integrator_name)]
    draw = 2
    while True:
        round_began = clock()
        passes = _passes(todo, comps, by_key, params)  # reads the scene: once a round
        for s in sensors:
            seeds = (_draw(job.seed, draw), _draw(job.seed, draw + 1))
            traced = ((recorded or split_samples).trace(scene, integrator, s, spp, seeds[0])
                      if split and any(
                forward_mode(by_key[comps[ks[0]].key], integrator_name) for ks in passes)
                else None)
            for ks in passes:
                q = by_key[comps[ks[0]].key]
                pair = _columns(scene, params, integrator, integrator_name, q,
                                [comps[k].index for k in ks], s, spp, seeds, together, traced,
                                comps[ks[0]].mode, recorded)
                for n, new in enumerate(pair):
                    for k, column in zip(ks, new):
                        old = columns[s][n][k]
                        columns[s][n][k] = column if old is None else (
                            (old * samples[k] + column * spp) / (samples[k] + spp))
                yield from clock.piece()
        samples[todo] += spp
        draw += 2
        fit = linearized([rows(s, sensor, renders[s], columns[s], comps, job, len(sensors))
                           for s, sensor in sensors.items()], job.loss)
        signal = np.diag(fit.hessian) / np.maximum(np.diag(fit.spread), 1e-300)
        short = [k for k in todo if signal[k] < SIGNAL and samples[k] < MAX_SAMPLES * job.spp]
        # the next round: 4x the samples for the components short of SIGNAL, at what this
        # round took per pass (a colour's three components are one) scaled by the cost model
        # (small images cost little more at 4x the spp)
        then = (clock() - round_began) * (
            len(_passes(short, comps, by_key, params)) / len(passes)) * (
            cost(4 * spp) / cost(spp))
        if fixed or not short or clock() - began + then > budget:
            break
        todo, spp = short, spp * 4
    return Linearization(comps, fit, clock() - began,
                         [] if recorded is None else [
                             f"standard errors: J's passes frozen ({recorded.recordings} "
                             "recordings" + ("" if recorded.inside else "; the tangents "
                                             "carried outside them, to values the scene "
                                             "derives at update()") + ")"])


def _draw(seed: int, n: int) -> int:
    return (seed * 1_000_003 + DRAW + 7919 * n) % 2**32


def _samples(budget: float, passes: int, cost, spp: int) -> int:
    """spp of each J estimate: the job's, or fewer (a power of 2, at least 1) so that
    ``passes`` (each two estimates) take about ``budget`` seconds, ``cost(s)`` each: renders
    cost about their time at 1 spp (tracing and launching, which small images are made of)
    plus a share of the rest by their spp."""
    s = spp
    # halved while over the budget, but not where halving saves little (small images are
    # mostly tracing and launching: 8 spp cost what 1 does, with 8 times the noise)
    while s > 1 and passes * cost(s) > budget and cost(s // 2) < 0.8 * cost(s):
        s //= 2
    return s


def _render(scene, params, integrator, sensor: int, spp: int, seed: int) -> np.ndarray:
    with dr.suspend_grad():
        img = mi.render(scene, params, sensor=sensor, spp=spp, integrator=integrator, seed=seed)
    return np.array(img, dtype=np.float64)[..., :3]


def _latent_step(q: Quantity) -> float:
    if q.eta:
        return ETA_STEP
    if q.log:
        return LOG_STEP
    span = q.hi - q.lo
    return LINEAR_STEP * (span if math.isfinite(span) else max(float(np.max(np.abs(q.value))),
                                                                 0.1))


def _direction(q: Quantity, indices: list[int], mode: int = 0) -> np.ndarray:
    """The latent change per unit of the components ``indices`` together (of a texture or
    grid: channels, in ``mode``)."""
    t = np.zeros(q.value.size, dtype=np.float64)
    weight = basis(q, mode) if q.channels else None
    for index in indices:
        if q.channels:
            t[index::q.channels] = weight[index::q.channels]
        else:
            t[index] = 1.0
    return t


def _tangent(q: Quantity, indices: list[int], mode: int = 0) -> np.ndarray:
    """The value's change per unit of the latent components ``indices`` together (times v
    for log)."""
    t = _direction(q, indices, mode)
    return t * q.value if q.log else t


def _passes(todo: list[int], comps: list[_Component], by_key: dict[str, Quantity],
            params: mi.SceneParameters) -> list[list[int]]:
    """The components of ``todo`` that each J pass estimates: one each, but a colour's three
    (or an RGB texture's levels) in one pass where the render keeps colour channels apart:
    then a pixel's red channel depends on the red component alone, so a pass that moves all
    three at once reads each one's column off its own channel (a third of the passes)."""
    out: dict[tuple[str, int], list[int]] = {}
    singles = []
    for k in todo:
        q = by_key[comps[k].key]
        if _channels_apart(q, params):
            out.setdefault((q.key, comps[k].mode), []).append(k)
        else:
            singles.append([k])
    return [*out.values(), *singles]


def _channels_apart(q: Quantity, params: mi.SceneParameters) -> bool:
    """Whether the render's channel c depends on component c of ``q`` alone: an RGB colour
    (or texture) in an RGB variant, where light transport multiplies channel by channel.
    A spectral variant mixes them (a colour is upsampled to a spectrum), and so does a
    principled BSDF with a specular or sheen tint (its base colour's luminance tints the
    lobes); sampling that reads a colour's luminance only moves the noise."""
    if (q.channels or q.value.size) != 3 or q.difference or not mi.is_rgb:
        return False
    prefix = q.key.removesuffix("base_color.value")
    if prefix == q.key:
        return True
    return all(float(np.max(np.asarray(params[prefix + name]))) == 0.0
               for name in ("spec_tint.value", "sheen.value") if prefix + name in params)


def _columns(scene, params, integrator, integrator_name: str, q: Quantity,
             indices: list[int], sensor: int, spp: int, seeds: tuple[int, int],
             together: list[Quantity], traced: split_samples.Traced | None, mode: int = 0,
             recorded: split_samples.Frozen | None = None
             ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """d(render)/d(latent component) for each of ``indices`` as (H, W, 3) images, twice from
    independent samples, from passes that move them together (several only where
    ``_passes`` packed a colour's channels: component c is then read off channel c).
    ``together``: every quantity whose J comes in forward mode (``forward_mode``);
    ``traced``: this round's rays and primal pass, when the integrator's forward mode can
    reuse them (split_samples: both estimates from one pass), else None. ``mode``: of a
    texture or grid, which of MODES; ``recorded``: the passes frozen, else None."""
    tangent = _tangent(q, indices, mode)
    if not forward_mode(q, integrator_name):
        h = _latent_step(q)
        direction = _direction(q, indices, mode)
        sides = []
        for sign in (-1.0, 1.0):
            if q.log:
                moved = q.value * np.exp(sign * h * direction)
            else:
                moved = q.value + sign * h * direction
            # a bound is not crossed: the step shortens on that side
            moved = np.clip(moved, max(q.lo, q.floor), q.hi)
            params[q.key] = side = parameters.assign(params[q.key], moved)
            dr.make_opaque(side)  # as in forward mode: one kernel for every component
            params.update()
            # the same samples on both sides, other samples for the other estimate
            if recorded is not None:
                images = recorded.primal(scene, integrator, sensor, spp, seeds[0])
            elif split_samples.shares_primal(integrator):
                images = split_samples.primal(split_samples.trace(
                    scene, integrator, sensor, spp, seeds[0]), integrator)
            else:
                images = tuple(_render(scene, params, integrator, sensor, spp, seed)
                               for seed in seeds)
            sides.append((moved, images))
        params[q.key] = parameters.assign(params[q.key], q.value)
        params.update()
        (a, images_a), (b, images_b) = sides
        latent = (np.log(np.maximum(b, 1e-30)) - np.log(np.maximum(a, 1e-30))) if q.log \
            else (b - a)
        return tuple([_channel(image_b - image_a, index, len(indices),
                               _width(latent, _direction(q, [index], mode)))
                 for index in indices]
                     for image_a, image_b in zip(images_a, images_b))
    # Every forward-mode quantity is a leaf of every pass, its tangent 0 but for q's: each
    # pass then traces the same kernel, compiled once rather than once per quantity. Opaque:
    # a literal value or tangent would be compiled into the kernel (0.2 s each at 128x96).
    leaves = {}
    for other in together:
        leaves[other.key] = leaf = parameters.assign(params[other.key], other.value)
        dr.make_opaque(leaf)
        dr.enable_grad(leaf)
        params[other.key] = leaf
    params.update()
    directions = []
    for other in together:
        directions.append(parameters.assign(leaves[other.key], tangent if other.key == q.key
                                            else np.zeros(other.value.size)))
        dr.make_opaque(directions[-1])
    if recorded is not None and traced is not None:
        images = recorded.forward(traced, scene, params, integrator, list(leaves), directions)
    else:
        # The tangent reaches what the plugin derives from the value at update() (a
        # dielectric's 1/eta) before the render, whose forward pass only follows edges made
        # inside it.
        split_samples.tangents(list(leaves.values()), directions)
        if traced is not None:
            images = split_samples.forward(traced, scene, integrator)
        else:
            images = tuple(np.array(integrator.render_forward(
                scene, params, sensor=sensor, seed=seed, spp=spp), dtype=np.float64)[..., :3]
                for seed in seeds)
    for other in together:
        params[other.key] = parameters.assign(params[other.key], other.value)
    params.update()
    return tuple([_channel(image, index, len(indices), 1.0) for index in indices]
                 for image in images)


def forward_mode(q: Quantity, integrator_name: str) -> bool:
    """Whether ``q``'s J comes from Mitsuba's forward mode (else from central differences)."""
    return not q.difference and integrator_name in FORWARD_MODE


def _width(latent: np.ndarray, moved: np.ndarray) -> float:
    """The latent distance between a difference's two sides, in units of ``moved`` (the
    direction's weight per element: a ramp moves its ends furthest), over the elements it
    moves."""
    on = moved != 0
    step = np.abs(latent[on] / moved[on])
    return float(np.max(step)) if step.size and np.any(step) else 0.0


def _channel(image: np.ndarray, index: int, packed: int, width: float) -> np.ndarray:
    """A column from a pass's image: all of it for a pass of one component, else channel
    ``index`` alone; over ``width`` (a difference's, 0: no slope)."""
    if width <= 0:
        return np.zeros_like(image)
    return (image if packed == 1 else image * (np.arange(3) == index)) / width


