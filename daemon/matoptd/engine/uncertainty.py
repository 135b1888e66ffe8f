"""A standard error for each recovered value of a kept iteration: ``covariance.py``'s model,
fed from the job's own scene, references, loss and Adam state.

J, the derivative of each rendered pixel with respect to each component (in the latent
coordinates Adam steps on), comes one pass per component (a colour's three in one pass where
the render keeps channels apart: ``_passes``): Mitsuba's forward mode (``render_forward``)
where the integrator has it, else a central difference of two renders with the same samples.
prbvolpath has no forward mode; a dielectric's eta is differenced always: near the specular
limit prb's derivative misses where the refracted rays go, and elsewhere it agrees with the
difference but is far noisier (a rough glass ball at 64 spp: J^T J to within 67% against
10%). Each column is estimated twice from independent samples, and only products across the
two enter J^T J, so J's own noise does not inflate it; with prb, prb_basic and prbvolpath both
estimates come from one pass at twice the samples, and every forward pass of a round replays
one primal pass (split_samples.py). A column whose J^T J its noise still swamps gets more
samples (``linearize``). A gain's column is the gained render's channel itself. A texture or
grid enters as its mean level per channel (one direction: every texel moved together), which
is what trades against a scalar (a medium's albedo grid against its sigma_t); a standard
error per texel would take one pass per texel.

The render noise (S_r) and the residual of the mean render (S_R: the reference's own noise
and what the scene does not model) come from two more renders A, B at the job's spp:
(A - B)^2 / 2 and (A - R)(B - R) per pixel-channel, both unbiased; the second, far the
noisier, is pooled over the image unless it shows a misfit (covariance.residual_noise).

Losses: ``mse`` and ``dual_buffer`` are least squares (dual_buffer's gradient averages two
renders, halving the noise a step sees); ``multiscale_mse`` is least squares on an image
pyramid, carried exactly by its (linear) pyramid operator; ``brightness_independent_mse`` is
least squares on images divided by their means, linearized. ``mae`` is not least squares: its
estimate is that of the least-squares fit to one render (the L2 approximation), which a note
says.

Over 500 lines: estimating J (``linearize``) and reading the estimate from it (``estimate``)
share the component and image layouts declared here; the algebra is in ``covariance.py``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import engine_api as api
from ..range_notes import at_bound
from . import covariance, parameters, split_samples
from .diagnosis import DECIDER, DECIDERS
from .optimize import Best, Optimization, schedule_factor

FORWARD_MODE = ("prb", "prb_projective", "direct_projective")  # integrators with render_forward
MAX_COMPONENTS = 48   # "a few dozen": J costs a pass per component
BUDGET = 0.1          # of the job's optimizing time, for all of J (its spp follows, down to 1)
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
    channels: int = 0      # > 0: a texture or grid, estimated as its mean level per channel
    difference: bool = False  # J by a central difference (a dielectric's eta)
    eta: bool = False      # a dielectric's eta (its difference step)


@dataclass
class Sensor:
    """A sensor's reference as the loss sees it."""

    reference: np.ndarray          # (H, W, 3)
    weight: np.ndarray | None      # (H, W, 3) mask weight, None: every pixel counts
    gain: np.ndarray | None = None  # RGB exposure gain (fit_exposure), optimized in log
    name: str = ""


@dataclass
class Adam:
    """Adam's state of one quantity (or gain) and the learning rate of each step taken."""

    second_moment: np.ndarray   # raw, flat, at its current level
    count: int
    rates: np.ndarray           # (steps,)
    gradients: np.ndarray | None = None  # (n, components) recorded, latent


@dataclass
class Job:
    """What the estimate needs from the job besides its values."""

    loss: str
    spp: int
    seed: int
    clamp: bool
    seconds: float              # its optimizing time so far (J may take BUDGET of it)


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


@dataclass
class _Component:
    name: str       # for notes: "key", "key[1]", "key (mean level, channel 0)", "gain of x[2]"
    key: str        # the quantity's key, or "" for a gain
    index: int      # component of the value, or channel of a level or a gain
    sensor: int = -1  # for a gain


def components(quantities: list[Quantity], sensors: dict[int, Sensor]) -> list[_Component]:
    out = []
    for q in quantities:
        if q.channels:
            out += [_Component(f"{q.key} (mean level" + (f", channel {c})" if q.channels > 1
                                                          else ")"), q.key, c)
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


def linearize(scene: mi.Scene, params: mi.SceneParameters, integrator: mi.Integrator,
              integrator_name: str, quantities: list[Quantity], sensors: dict[int, Sensor],
              job: Job) -> Linearization:
    """J, the render noise and the residual at the values ``params`` holds (set by the
    caller to ``quantities``' values), as H, Q and Q_R.

    J is first estimated at the spp that half the budget allows (_samples); a component
    whose J^T J is then less than SIGNAL times its own noise gets more samples, four times as
    many a round, while the whole fits in the budget: a derivative image can be far
    noisier than its render (a glass ball's eta at 16 spp: noise ten times the signal), and a
    standard error from a J^T J that noise swamps would be noise too."""
    began = time.perf_counter()
    comps = components(quantities, sensors)
    if len(comps) > MAX_COMPONENTS:
        return Linearization(comps, None)
    by_key = {q.key: q for q in quantities}
    renders = {s: [_render(scene, params, integrator, s, job.spp, _draw(job.seed, n))
                   for n in (0, 1)] for s in sensors}
    full = (time.perf_counter() - began) / (2 * len(sensors))
    began_one = time.perf_counter()
    _render(scene, params, integrator, next(iter(sensors)), 1, _draw(job.seed, 9))
    one = time.perf_counter() - began_one
    budget = min(BUDGET * job.seconds, BUDGET_CAP)
    count = len(sensors) * len(_passes([k for k, c in enumerate(comps) if c.key],
                                       comps, by_key, params))
    split = split_samples.shares_primal(integrator)

    def render(s: int) -> float:  # its time at 1 spp plus a share of the rest by its spp
        return one + max(full - one, 0) * (s - 1) / max(job.spp - 1, 1)

    def cost(s: int) -> float:  # of a pass's two estimates at s spp each
        # split: one forward pass at 2s (its primal shared), about two renders' work;
        # else two estimates of a primal and a forward pass (or two sides) each
        return 2 * render(2 * s) if split else 4 * render(s)

    spp = _samples(budget / 2 - (time.perf_counter() - began), count, cost, job.spp)
    # columns[sensor][n][k]: estimate n (of two) of component k's column, over samples[k]
    columns = {s: [[None] * len(comps) for _ in (0, 1)] for s in sensors}
    samples = np.zeros(len(comps))
    todo = [k for k, c in enumerate(comps) if c.key]
    together = [q for q in quantities if forward_mode(q, integrator_name)]
    draw = 2
    while True:
        round_began = time.perf_counter()
        passes = _passes(todo, comps, by_key, params)  # reads the scene: once a round
        for s in sensors:
            seeds = (_draw(job.seed, draw), _draw(job.seed, draw + 1))
            traced = (split_samples.trace(scene, integrator, s, spp, seeds[0]) if split and any(
                forward_mode(by_key[comps[ks[0]].key], integrator_name) for ks in passes)
                else None)
            for ks in passes:
                q = by_key[comps[ks[0]].key]
                pair = _columns(scene, params, integrator, integrator_name, q,
                                [comps[k].index for k in ks], s, spp, seeds, together, traced)
                for n, new in enumerate(pair):
                    for k, column in zip(ks, new):
                        old = columns[s][n][k]
                        columns[s][n][k] = column if old is None else (
                            (old * samples[k] + column * spp) / (samples[k] + spp))
        samples[todo] += spp
        draw += 2
        fit = _linearized([_rows(s, sensor, renders[s], columns[s], comps, job, len(sensors))
                           for s, sensor in sensors.items()], job.loss)
        signal = np.diag(fit.hessian) / np.maximum(np.diag(fit.spread), 1e-300)
        short = [k for k in todo if signal[k] < SIGNAL and samples[k] < MAX_SAMPLES * job.spp]
        # the next round: 4x the samples for the components short of SIGNAL, at what this
        # round took per pass (a colour's three components are one) scaled by the cost model
        # (small images cost little more at 4x the spp)
        then = (time.perf_counter() - round_began) * (
            len(_passes(short, comps, by_key, params)) / len(passes)) * (
            cost(4 * spp) / cost(spp))
        if not short or time.perf_counter() - began + then > budget:
            break
        todo, spp = short, spp * 4
    return Linearization(comps, fit, time.perf_counter() - began)


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
    errors, gains, notes = _report(comps, quantities, sensors, result, job)
    owner = [c.key or f"gain{c.sensor}" for c in comps]
    index = {c.name: i for i, c in enumerate(comps)}
    traded = {frozenset((owner[index[a]], owner[index[b]]))
              for a, b, _ in covariance.correlated(result.noise, result.determined,
                                                   list(index))}
    return Estimate(errors, gains, notes, list(index), result.covariance,
                    linearization.seconds, {t for t in traded if len(t) == 2},
                    {owner[i] for i in np.flatnonzero(~result.determined)})


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


def _tangent(q: Quantity, indices: list[int]) -> np.ndarray:
    """The value's change per unit of the latent components ``indices`` together (v for
    log, 1 otherwise)."""
    t = np.zeros(q.value.size, dtype=np.float64)
    for index in indices:
        if q.channels:
            t[index::q.channels] = 1.0
        else:
            t[index] = 1.0
    return t * q.value if q.log else t


def _passes(todo: list[int], comps: list[_Component], by_key: dict[str, Quantity],
            params: mi.SceneParameters) -> list[list[int]]:
    """The components of ``todo`` that each J pass estimates: one each, but a colour's three
    (or an RGB texture's levels) in one pass where the render keeps colour channels apart:
    then a pixel's red channel depends on the red component alone, so a pass that moves all
    three at once reads each one's column off its own channel (a third of the passes)."""
    out: dict[str, list[int]] = {}
    singles = []
    for k in todo:
        q = by_key[comps[k].key]
        if _channels_apart(q, params):
            out.setdefault(q.key, []).append(k)
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
             together: list[Quantity], traced: split_samples.Traced | None
             ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """d(render)/d(latent component) for each of ``indices`` as (H, W, 3) images, twice from
    independent samples, from passes that move them together (several only where
    ``_passes`` packed a colour's channels: component c is then read off channel c).
    ``together``: every quantity whose J comes in forward mode (``forward_mode``);
    ``traced``: this round's rays and primal pass, when the integrator's forward mode can
    reuse them (split_samples: both estimates from one pass), else None."""
    tangent = _tangent(q, indices)
    if not forward_mode(q, integrator_name):
        h = _latent_step(q)
        sides = []
        for sign in (-1.0, 1.0):
            if q.log:
                moved = q.value * np.exp(sign * h * (tangent != 0))
            else:
                moved = q.value + sign * h * tangent
            # a bound is not crossed: the step shortens on that side
            moved = np.clip(moved, max(q.lo, q.floor), q.hi)
            params[q.key] = side = parameters.assign(params[q.key], moved)
            dr.make_opaque(side)  # as in forward mode: one kernel for every component
            params.update()
            # the same samples on both sides, other samples for the other estimate
            if split_samples.shares_primal(integrator):
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
                               _width(latent, _tangent(q, [index]))) for index in indices]
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
    # The tangent reaches what the plugin derives from the value at update() (a dielectric's
    # 1/eta) before the render, whose forward pass only follows edges made inside it.
    for other in together:
        leaf = leaves[other.key]
        direction = parameters.assign(leaf, tangent if other.key == q.key
                                      else np.zeros(other.value.size))
        dr.make_opaque(direction)
        dr.set_grad(leaf, direction)
        dr.enqueue(dr.ADMode.Forward, leaf)
    dr.traverse(dr.ADMode.Forward, dr.ADFlag.ClearEdges)
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
    """The latent distance between a difference's two sides, over the elements ``moved``."""
    step = np.abs(latent[moved != 0])
    return float(np.max(step)) if step.size and np.any(step) else 0.0


def _channel(image: np.ndarray, index: int, packed: int, width: float) -> np.ndarray:
    """A column from a pass's image: all of it for a pass of one component, else channel
    ``index`` alone; over ``width`` (a difference's, 0: no slope)."""
    if width <= 0:
        return np.zeros_like(image)
    return (image if packed == 1 else image * (np.arange(3) == index)) / width


@dataclass
class _Rows:
    """One sensor's pixel-channels, flattened: two estimates of J (rows x p), the same
    weighted by the loss (K J), the render noise and the residual per row."""

    ja: np.ndarray
    jb: np.ndarray
    ka: np.ndarray
    kb: np.ndarray
    weight: np.ndarray    # the loss's own weight of each row (multiscale: its full level's)
    noise: np.ndarray
    residual: np.ndarray


def _rows(index: int, sensor: Sensor, renders: list[np.ndarray],
          pair: list[list[np.ndarray | None]],
          comps: list[_Component], job: Job, count: int) -> _Rows:
    gain = sensor.gain if sensor.gain is not None else np.ones(3)
    a, b = (r * gain for r in renders)
    ref = sensor.reference.astype(np.float64)
    weight = (np.ones_like(ref) if sensor.weight is None
              else sensor.weight.astype(np.float64))
    if job.clamp:  # compared in [0, 1]: a clipped pixel has no slope
        weight = weight * ((a + b) / 2 < 1.0)
        ref = np.clip(ref, 0.0, 1.0)
    estimates = []
    for n, cols in enumerate(pair):
        image = (a, b)[n]
        j = [col * gain if col is not None else
             image * ((np.arange(3) == c.index) & (c.sensor == index))
             for col, c in zip(cols, comps)]
        estimates.append(np.stack(j, axis=-1))  # (H, W, 3, p)
    ja, jb = estimates
    if job.loss == "brightness_independent_mse":
        ja, jb, a, b, ref = _normalized(ja, jb, a, b, ref, weight)
    noise = (a - b) ** 2 / 2
    residual = (a - ref) * (b - ref)
    # The loss's weight of each row, as losses._mean: sum(w x) / max(sum(w), 1), mean over
    # sensors; multiscale_mse adds the pyramid's levels (K = sum_l D_l^T C_l D_l).
    c = weight / max(float(weight.sum()), 1.0) / count
    if job.loss == "multiscale_mse":
        ka, kb = (_pyramid(j, weight) / count for j in (ja, jb))
    else:
        ka, kb = ja * c[..., None], jb * c[..., None]
    p = ja.shape[-1]
    flat = (lambda x: x.reshape(-1, p))
    return _Rows(flat(ja), flat(jb), flat(ka), flat(kb), c.ravel(), noise.ravel(),
                 residual.ravel())


def _normalized(ja, jb, a, b, ref, weight):
    """brightness_independent_mse's images, I / (mean_w I + eps), and J through that map
    (linearized at the mean render)."""
    eps = 1e-3  # losses.EPSILON
    total = max(float(weight.sum()), 1.0)
    mean = float(np.sum(weight * (a + b) / 2)) / total + eps
    level = (a + b) / 2

    def through(j):
        slope = np.sum(weight[..., None] * j, axis=(0, 1, 2)) / total
        return j / mean - level[..., None] * slope / mean ** 2

    ref_mean = float(np.sum(weight * ref)) / total + eps
    return (through(ja), through(jb), a / (float(np.sum(weight * a)) / total + eps),
            b / (float(np.sum(weight * b)) / total + eps), ref / ref_mean)


def _half(x: np.ndarray) -> np.ndarray:
    """losses.half on numpy: 2x2 box average over the first two axes, odd ones dropped."""
    h, w = x.shape[0] // 2 * 2, x.shape[1] // 2 * 2
    x = x[:h, :w]
    return 0.25 * (x[0::2, 0::2] + x[1::2, 0::2] + x[0::2, 1::2] + x[1::2, 1::2])


def _half_adjoint(x: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    out = np.zeros(shape + x.shape[2:])
    for dy in (0, 1):
        for dx in (0, 1):
            out[dy:2 * x.shape[0]:2, dx:2 * x.shape[1]:2] = 0.25 * x
    return out


def _pyramid(j: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """K J for multiscale_mse: sum over its levels of D_l^T C_l D_l J (losses._multiscale)."""
    total = j * (weight / max(float(weight.sum()), 1.0))[..., None]
    levels = [(j, weight)]
    while min(levels[-1][0].shape[:2]) >= 16:
        x, w = levels[-1]
        levels.append((_half(x), _half(w)))
        back = levels[-1][0] * (levels[-1][1] / max(float(levels[-1][1].sum()), 1.0))[..., None]
        for finer in reversed(levels[:-1]):
            back = _half_adjoint(back, finer[0].shape[:2])
        total = total + back
    return total


def _linearized(rows: list[_Rows], loss: str) -> covariance.Linearized:
    p = rows[0].ja.shape[1]
    h, spread, q, qr = (np.zeros((p, p)) for _ in range(4))
    k = 2.0 if loss == "dual_buffer" else 4.0
    for r in rows:
        h += 2 * covariance.crossed(r.ja, r.kb, np.ones(len(r.ja)))[0]
        spread = np.sqrt(spread ** 2 + (2 * covariance.crossed(r.ja, r.jb, r.weight)[1]) ** 2)
        q += k * covariance.crossed(r.ka, r.kb, r.noise)[0]
        qr += 4 * covariance.residual_noise(r.ka, r.kb, r.noise, r.residual, r.weight)
    return covariance.Linearized(h, q, qr, spread)


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
    for i, c in enumerate(comps):
        a = adam[c.key or f"gain{c.sensor}"]
        rates[:, i] = a.rates
        q = by_key.get(c.key)
        if q is not None and q.channels:
            # A mean level moves by the mean of its texels' steps: d = mean(d_k) / n_c,
            # held as an equivalent second moment (Adam's v is the texels').
            v = a.second_moment.reshape(-1, q.channels)[:, c.index] / (1 - covariance.BETA_2
                                                                       ** max(a.count, 1))
            per = np.mean(1 / (np.sqrt(v) + covariance.EPSILON))
            level = (len(v) / per) ** 2
            second[i] = level * (1 - covariance.BETA_2 ** max(count, 1))
            measured[i] = False
            continue
        second[i] = a.second_moment[c.index]
        if a.gradients is not None and len(a.gradients):
            gradients[-len(a.gradients):, i] = a.gradients[:, c.index]
    return covariance.Dynamics(rates, second, count, measured, gradients)


def _report(comps: list[_Component], quantities: list[Quantity], sensors: dict[int, Sensor],
            result: covariance.Estimate, job: Job
            ) -> tuple[dict[str, api.StandardError], dict[int, api.StandardError], list[str]]:
    """Standard errors on the value's scale (log ones by the delta method, v * se(log v)),
    how to read each component, and the notes."""
    sd = np.sqrt(np.maximum(np.diag(result.covariance), 0))
    errors: dict[str, api.StandardError] = {}
    notes: list[str] = []
    start = 0
    for q in quantities:
        n = q.channels or q.value.size
        latent, ok = sd[start:start + n], result.determined[start:start + n]
        start += n
        if q.channels:
            level = q.value.reshape(-1, q.channels).mean(axis=0)
            shown = np.where(ok, latent * (level if q.log else 1.0), np.inf)
            notes.append(
                f"{q.key}: its mean level is known to +- " + ", ".join(_short(shown)) +
                " (one standard error" + (" per channel" if q.channels > 1 else "") +
                ", its texels' pattern held as recovered); no standard error per texel: "
                f"that would take a render pass per texel ({q.value.size // q.channels})")
            continue
        value = q.value.astype(np.float64)
        error = np.where(ok, latent * (value if q.log else 1.0), np.inf)
        lower = np.maximum(q.lo, q.floor)
        low = at_bound(value, lower) | ((q.floor > 0) & (value <= q.floor + 1e-6))
        high = at_bound(value, q.hi)
        reading = ["not_determined" if not d else "at_lower_bound" if lo else
                   "at_upper_bound" if hi else "two_sided" for d, lo, hi in zip(ok, low, high)]
        errors[q.key] = api.StandardError(error.astype(np.float32), reading)
        span = (np.log(q.hi / lower) if q.log and lower > 0 and math.isfinite(q.hi)
                else q.hi - q.lo if not q.log else math.inf)
        wide = ok & (latent > 0.25 * (span if math.isfinite(span) else 1.0))
        for c in np.flatnonzero(wide):
            what = (f"more than a quarter of its range [{q.lo:g}, {q.hi:g}]"
                    if math.isfinite(span) else "more than a quarter of its value")
            notes.append(f"{_name(q, c)}: standard error {error[c]:.3g}, {what}: these "
                         f"images do not decide it; what would: {DECIDER}")
        for c in np.flatnonzero(ok & (low | high)):
            bound = lower if low[c] else q.hi
            where = "its floor" if low[c] and q.floor else "a bound"
            notes.append(f"{_name(q, c)}: ended at {where} "
                         f"{bound:g}, so its interval is one-sided: the truth lies within "
                         f"{'+' if low[c] else '-'}{2 * error[c]:.3g} of it (two standard "
                         "errors, on the side away from the bound)")
    gains: dict[int, api.StandardError] = {}
    for s, sensor in sensors.items():
        if sensor.gain is None:
            continue
        latent, ok = sd[start:start + 3], result.determined[start:start + 3]
        start += 3
        gains[s] = api.StandardError(
            np.where(ok, latent * sensor.gain, np.inf).astype(np.float32),
            ["two_sided" if d else "not_determined" for d in ok])
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
    if job.loss == "mae":
        notes.append("standard errors are those of a least-squares fit to one render (the "
                     "L2 approximation): mae is not least squares, and how far Adam's last "
                     "steps scatter is not modelled for it")
    return errors, gains, notes


def _name(q: Quantity, c: int) -> str:
    return q.key if q.value.size == 1 else f"{q.key}[{c}]"


def _short(v: np.ndarray) -> list[str]:
    return [f"{x:.3g}" if np.isfinite(x) else "not determined" for x in np.ravel(v)]




# -- from a job's optimization ----------------------------------------------------------------

def of_kept(opt: Optimization, chosen: list[tuple[str, Best]], kinds: dict[str, str]
            ) -> dict[str, Estimate]:
    """Estimates for a job's kept iterations (best, last), read from its Optimization; an
    estimate that fails leaves the results as they are, with a note saying why."""
    try:
        return _of_kept(opt, chosen, kinds)
    except Exception as exc:  # noqa: BLE001 - the job's results stand without them
        note = f"standard errors: not estimated ({type(exc).__name__}: {exc})"
        return {which: Estimate({}, {}, [note]) for which, _ in chosen}


def _of_kept(opt: Optimization, chosen: list[tuple[str, Best]], kinds: dict[str, str]
             ) -> dict[str, Estimate]:
    """The images are linearized at the last iteration, and again at the best only when it
    lies further from it than two difference steps (over which J is taken as constant
    anyway) and the first kept within its share of the time J may take."""
    kept = []
    for which, it in sorted(chosen, key=lambda c: c[0] != "last"):
        quantities, skipped = _quantities(opt, it, kinds)
        sensors = {s: Sensor(np.asarray(ref.image), None if ref.weight is None
                             else np.asarray(ref.weight),
                             it.gains.get(s) if s in opt.gains else None, ref.name)
                   for s, ref in opt.references.items()}
        kept.append((which, it, quantities, sensors, skipped))
    apart = [k for k in kept[1:] if not _near(k[2], kept[0][2])] if kept else []
    job = Job(opt.settings.loss, opt.spp, opt.settings.seed, opt.settings.clamp,
              opt.elapsed / (1 + len(apart)))
    out: dict[str, Estimate] = {}
    linearized: Linearization | None = None
    began = time.perf_counter()
    count, reused = 0, ""
    for which, it, quantities, sensors, skipped in kept:
        if linearized is None or any(which == k[0] for k in apart):
            # A second linearization only where the first left it its share of the budget:
            # at the least spp a small image's J costs its passes' tracing, whatever the spp.
            if linearized is not None and linearized.seconds > BUDGET * job.seconds:
                reused = (f"; {which}'s from the linearization at {kept[0][0]}, since a "
                          "second would pass the time standard errors may take")
            else:
                with opt.holding(it.values):
                    linearized = linearize(opt.scene, opt.params, opt.integrator,
                                           opt.integrator_name, quantities, sensors, job)
                count += 1
        adam = None if job.loss == "mae" else _adam(opt, it)
        out[which] = estimate(linearized, quantities, sensors, job, adam)
        out[which].notes[:0] = skipped
    seconds = time.perf_counter() - began
    for e in out.values():
        e.seconds = seconds
        if e.names:
            e.notes.append(f"standard errors: {len(e.names)} components, {seconds:.2g} s "
                           f"({100 * seconds / max(opt.elapsed, 1e-9):.0f}% of the job's "
                           f"optimizing time{', two linearizations' if count > 1 else ''}"
                           f"{reused})")
    return out


def _quantities(opt: Optimization, kept: Best, kinds: dict[str, str]
                ) -> tuple[list[Quantity], list[str]]:
    out, skipped = [], []
    for key, k in opt.kept.items():
        value = np.asarray(kept.values[key], dtype=np.float64)
        summarized = kinds.get(key) in ("texture", "volume_grid")
        if value.size > api.SMALL and not summarized:
            skipped.append(f"{key}: no standard error ({value.size} components; only scalars, "
                           "colours, textures and grids are estimated)")
            continue
        eta = parameters.dielectric_eta(key)  # the log_space choice's kept range is v's
        out.append(Quantity(key, value, k.log, k.lo, k.hi, k.floor,
                            max(opt.channels(key), 1) if summarized else 0, eta, eta))
    return out, skipped


def _adam(opt: Optimization, kept: Best) -> dict[str, Adam]:
    """Adam's state now, and the learning rate of each step that led to ``kept``."""
    c = opt.settings
    per = (len(opt.references) if c.sensor_mode == "step_per_sensor"
           and len(opt.references) > 1 else 1)
    schedule = [schedule_factor(c, i) for i in range(max(kept.iteration, 0))]
    out = {}
    for key, rate in opt.rates.items():
        _, _, _, (t, _, v, _) = opt.opt.state[key]
        recorded = opt.gradients.get(key)
        held = set(opt.held.get(key, ()))  # a held step moved nothing
        factors = np.repeat([0.0 if i in held else f for i, f in enumerate(schedule)], per)
        out[key] = Adam(np.asarray(v, dtype=np.float64).ravel(),
                        int(np.asarray(t).ravel()[0]), rate * factors,
                        np.array([np.ravel(g) for g in recorded]) if recorded else None)
    return out


def _near(quantities: list[Quantity], others: list[Quantity]) -> bool:
    """Whether every value lies within two difference steps (latent) of the other's."""
    for q, o in zip(quantities, others):
        u, w = ((np.log(np.maximum(x.value, 1e-30)) if q.log else x.value) for x in (q, o))
        if np.any(np.abs(u - w) > 2 * _latent_step(q)):
            return False
    return True
