"""One optimization: Adam on the selected parameters, one iteration at a time, so that the
scheduler can interleave jobs, pause them and checkpoint them between iterations.

An iteration i renders every sensor that has a reference with the parameters theta_i, takes
the loss L_i (mean over those sensors), records (i, L_i, theta_i), and then, unless this was
the last iteration or L_i < min_error, back-propagates and steps to theta_{i+1}. So the best
iteration's parameters are exactly the ones that produced its loss, and no step is taken whose
result would never be rendered. With ``step_per_sensor`` (the thesis tool's way) each sensor's
gradient is applied as soon as it is known; by default they accumulate into one step.

Guards (Dr.Jit 1.5's dr.clip propagates NaN, and Adam has no NaN guard of its own):
- a gradient component that is NaN/Inf is set to 0 before the step; with ``mask_updates``
  Adam then leaves that component and its moments alone. Counted in ``nonfinite_steps``.
- a loss that is NaN/Inf skips the step entirely. Counted in ``skipped_steps``.
- after the step each parameter is clipped into its [min, max]; components the step pushed
  out are counted in ``clamped``.
The guards never wait for the device: their counts are symbolic sums, evaluated with the next
iteration's parameter values in one launch. The plain loop syncs once per iteration (reading
the loss); so does this one, and Python traces the next render while the backward pass runs.

Parameters that are positive and unbounded above (radiance, extinction, scales) are optimized
as u = log(v): a step of size lr changes v by a factor of about e^lr, the same relative change
at 1e-3 as at 1e3, so a radiance near 1000 and a reflectance near 0.5 can share one learning
rate, and v can never step below 0. Microfacet widths (roughness, alpha) are too, clipped in
log space to their range: a near-specular truth lies decades below the start. The others are
optimized as they are and clipped.

A dielectric's eta near the specular limit is the exception to back-propagation: prb and
prbvolpath sample the refracted direction detached from eta, so their gradient of eta lacks
where the refracted rays go, which decides the image once the lobe is narrow. While the
surface's alpha is below parameters.SPECULAR_ALPHA, eta's derivative is taken as a central
difference of the loss instead, both sides rendered with the same samples
(_difference_gradients). A texture or grid given a smoothness weight w descends
L + w * mean((v_a - v_b)^2) over neighbouring entries; the recorded loss is L alone.

With ``fit_exposure`` each reference also gets an RGB gain g (the photograph's unknown exposure
and white balance), optimized in log space with the parameters: the loss compares render * g
with the reference. Gains are not scene parameters: they travel beside theta, as ``gains``.
"""

from __future__ import annotations

import contextlib
import functools
import io
import math
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from . import multires, parameters
from ..truth import ParameterError, parameter_error
from .integrator import choose
from ..engine_api import SMALL
from .losses import LOSSES


@dataclass
class Setting:
    """One selected parameter, with everything defaulted and validated by the caller."""

    key: str
    learning_rate: float
    lo: float
    hi: float
    initial: np.ndarray | None  # None: the scene's value
    smoothness: float = 0.0     # weight of the texture's or grid's smoothness term

    @property
    def log(self) -> bool:
        return parameters.log_space(self.key, self.lo, self.hi)

    @functools.cached_property
    def floor(self) -> float:  # read by _value at every iteration
        return parameters.shown_floor(self.key, self.lo)

    def latent_bounds(self) -> tuple[float, float]:
        """[min, max] of u = log(v) for a log parameter."""
        lo, hi = parameters.log_bounds(self.key, self.lo, self.hi)
        return (math.log(lo) if lo > 0 else -LATENT_LIMIT,
                math.log(hi) if math.isfinite(hi) else LATENT_LIMIT)


@dataclass
class Reference:
    image: mi.TensorXf           # (H, W, 3), linear; masked pixels hold 0
    weight: mi.TensorXf | None   # (H, W, 3) in [0, 1]: the mask (and alpha) weight, 0 where the
                                 # reference was NaN/Inf; None when every pixel counts fully
    name: str = ""               # the user's file name, for notes

    def mask(self) -> np.ndarray:
        """The weight as an array (ones when there is none)."""
        if self.weight is None:
            return np.ones(tuple(int(s) for s in self.image.shape), dtype=np.float32)
        return np.asarray(self.weight)


@dataclass
class Config:
    loss: str  # a key of LOSSES
    iterations: int
    min_error: float
    spp: int
    seed: int
    cosine: bool = True
    step_per_sensor: bool = False
    clamp: bool = False
    truth: dict[str, np.ndarray] = field(default_factory=dict)
    channels: dict[str, int] = field(default_factory=dict)  # of textures and grids, for errors
    image_error_every: int = 0
    image_error_spp: int = 64
    fit_exposure: bool = False


GAIN_LEARNING_RATE = 0.1  # of log(gain): a step changes a gain by about 10%
GAIN_LIMIT = 10.0         # |log(gain)| bound: a factor of e^10 ~ 22000 either way


@dataclass
class Step:
    iteration: int
    loss: float
    values: dict[str, np.ndarray]  # theta_i (all selected parameters)
    done: bool
    stop_reason: str = ""
    errors: dict[str, ParameterError] = field(default_factory=dict)
    image_error: float | None = None
    gains: dict[int, np.ndarray] = field(default_factory=dict)  # sensor -> RGB gain


@dataclass
class Best:
    """An iteration and the parameters that produced its loss (the best so far, or the last)."""

    iteration: int = -1
    loss: float = math.inf
    values: dict[str, np.ndarray] = field(default_factory=dict)
    gains: dict[int, np.ndarray] = field(default_factory=dict)


def rate_factor(i: int, iterations: int, cosine: bool) -> float:
    """The learning rate of step i over the job's own: lr_i = lr * (0.1 + 0.9 * (1 +
    cos(pi * i / (N - 1))) / 2) under the cosine schedule, 1 under the constant one."""
    if not cosine or iterations < 2:
        return 1.0
    return 0.1 + 0.45 * (1.0 + math.cos(math.pi * i / (iterations - 1)))


def _seed(base: int, iteration: int, slot: int, slots: int) -> int:
    return (base * 1_000_003 + iteration * slots + slot) % 2**32


# The differences' renders take a quarter of the job's spp: both sides share their samples, so
# most noise cancels. On the Table 2 and 3 kinds eta ended as close as at full spp (0.0-0.5%)
# and an iteration took 25% less time.
DIFFERENCE_SPP_DIVISOR = 4
ETA_STEP = 0.01     # half the step of eta's central difference: 1% of the range near 1.5
LOG_FLOOR = 1e-6    # log(0) is -inf: a start at 0 starts at this instead
LATENT_LIMIT = 40.0  # |u| bound for log parameters: e^40 ~ 2e17, far past any scene


class Optimization:
    def __init__(self, scene: mi.Scene, settings: list[Setting],
                 references: dict[int, Reference], config: Config) -> None:
        self.scene = scene
        self.settings = {s.key: s for s in settings}
        self.references = dict(sorted(references.items()))
        self.config = config
        self.loss = LOSSES[config.loss]
        self.spp = config.spp
        self.integrator, self.integrator_name, self.integrator_reason = choose(
            scene, list(self.settings))

        self.params = mi.traverse(scene)
        self.scene_values = {k: parameters.flat(self.params[k]) for k in self.settings}
        # Dielectric etas get central differences while their surface is near-specular
        # (_difference_gradients): per eta, the widths beside it and the fixed ones' values.
        # Read from a traversal of their own: a key read through self.params is marked for
        # its update(), which then fails on the keys that keep() below drops.
        widths = mi.traverse(scene)
        self.differenced = {
            k: {w: parameters.flat(widths[w]) for w in
                parameters.microfacet_widths(k, widths.keys())}
            for k in self.settings if parameters.dielectric_eta(k)}
        del widths
        self.params.keep(list(self.settings))
        self._pending: list[tuple[str, mi.Float]] = []  # guard counts not yet read
        # per step, the gradient each small parameter and gain stepped on (latent), read
        # with the next theta: whether the images steered a drift (diagnosis), how noisy
        # the steps were (uncertainty)
        self.gradients: dict[str, list[np.ndarray]] = {}
        self._stepped: list[dict[str, object]] = []
        self.opt = mi.ad.Adam(lr=parameters.DEFAULT_LEARNING_RATE, mask_updates=True)
        # Textures and grids large enough go coarse to fine (multires.py): their shapes per
        # level, the level in use, and the gather map from the full shape to it.
        self.levels: dict[str, list[tuple[int, ...]]] = {}
        self.level: dict[str, int] = {}
        self._maps: dict[str, mi.UInt32 | None] = {}
        self.choices: list[str] = []  # what the optimization chose by itself, in words
        for key, s in self.settings.items():
            start = np.clip(s.initial if s.initial is not None else self.scene_values[key],
                            s.lo, s.hi)
            if parameters.black_tint(key, start):
                start = np.full_like(start, np.clip(parameters.NEUTRAL_START, s.lo, s.hi))
                self.choices.append(
                    f"{key}: started at {parameters.NEUTRAL_START:g} instead of black: a black "
                    "colour makes the lobes it tints black, and what they carry gets no gradient")
            if s.log:
                start = np.clip(np.log(np.maximum(start, LOG_FLOOR)), *s.latent_bounds())
            value = self.params[key]
            shapes = multires.levels(tuple(int(n) for n in value.shape)
                                     if dr.is_tensor_v(value) else ())
            if len(shapes) > 1:
                self.levels[key] = shapes
                self._set_level(key, 0, multires.downsample(start, shapes[-1], shapes[0]))
                steps = " -> ".join("x".join(map(str, sh[:-1])) for sh in shapes)
                self.choices.append(
                    f"{key}: optimized coarse to fine ({steps}; the full resolution from "
                    f"iteration {config.iterations // 2}): the pattern's low frequencies "
                    "settle before its detail")
            else:
                self.opt[key] = parameters.assign(value, start)
            self.opt.set_learning_rate({key: s.learning_rate})
        # Adam keys of the log gains, by sensor; the first iteration starts them (_start_gains).
        self.gains = {sensor: f"gain{sensor}" for sensor in self.references
                      } if config.fit_exposure else {}
        for key in self.gains.values():
            self.opt[key] = mi.Float(0.0, 0.0, 0.0)
            self.opt.set_learning_rate({key: GAIN_LEARNING_RATE})
        # Per textured key, its smoothness weight and the neighbour pairs at each level.
        self.smooth = {k: s.smoothness for k, s in self.settings.items() if s.smoothness > 0}
        self._pairs: dict[tuple[str, int], tuple[mi.UInt32, mi.UInt32]] = {}
        self._images: dict[int, list] = {}  # sensor -> this iteration's renders, detached
        for key, widths in self.differenced.items():
            when = (f"while {' and '.join(widths)} shows alpha < "
                    f"{parameters.SPECULAR_ALPHA:g}" if widths else "(a smooth dielectric)")
            self.choices.append(
                f"{key}: its gradient by central differences of the loss {when} (eta +- "
                f"{ETA_STEP:g}, the same samples on both sides): {self.integrator_name} samples "
                "the refracted direction detached from eta, so near the specular limit its own "
                "gradient of eta misses where the refracted rays go")
        self.rates = {**{k: s.learning_rate for k, s in self.settings.items()},
                      **{k: GAIN_LEARNING_RATE for k in self.gains.values()}}
        self._apply()
        self.initial = self.theta()[0]

        self.iteration = 0          # the next iteration to run
        self.elapsed = 0.0          # optimizing seconds, excluding pauses and other jobs' turns
        self.best = Best()
        self.last = Best()          # the latest iteration run
        self.nonfinite_steps = 0
        self.skipped_steps = 0
        self.clamped = 0
        self.recent: list[float] = []  # the last `loss.window` finite losses
        # per iteration, the mean of each parameter too large for the records (diagnosis)
        self.means: dict[str, list[float]] = {}
        self._judged: float | None = None

    # -- the loop ---------------------------------------------------------------------------

    def _value(self, key: str):
        """The scene value of a parameter, v = e^u for log parameters, blown up to the full
        shape for a texture at a coarse level (differentiable in u), and no less than the
        floor a principled roughness is shown at (parameters.ROUGHNESS_FLOOR)."""
        u = self.opt[key]
        index = self._maps.get(key)
        if index is not None:
            u = multires.upsample(u, self.levels[key][-1], index)
        v = dr.exp(u) if self.settings[key].log else u
        floor = self.settings[key].floor
        if floor > 0:  # rendered at max(v, floor), stepped on the floor's gradient below it
            v = v + dr.detach(dr.maximum(v, floor) - v)
        return v

    def _set_level(self, key: str, level: int, latent: np.ndarray) -> None:
        """Optimizes ``key`` at ``level`` from ``latent`` (flat, that level's shape); Adam's
        state starts afresh (the shape changes)."""
        shapes = self.levels[key]
        self.level[key] = level
        self.opt[key] = mi.TensorXf(np.asarray(latent, np.float32).reshape(shapes[level]))
        full = level == len(shapes) - 1
        self._maps[key] = None if full else mi.UInt32(multires.index_map(shapes[-1],
                                                                         shapes[level]))

    def _refine(self, i: int) -> None:
        """Moves textures and grids to the next level when iteration i reaches it."""
        changed = False
        for key, shapes in self.levels.items():
            level = multires.level_at(i, self.config.iterations, len(shapes))
            if level > self.level[key]:
                current = parameters.flat(self.opt[key])
                self._set_level(key, level, current[multires.index_map(
                    shapes[level], shapes[self.level[key]])])
                self.opt.set_learning_rate({key: self.settings[key].learning_rate})
                changed = True
        if changed:
            self._apply()

    def _apply(self) -> None:
        for key in self.settings:
            self.params[key] = self._value(key)
        self.params.update()

    def theta(self) -> tuple[dict[str, np.ndarray], dict[int, np.ndarray]]:
        """theta and the gains, read in one launch together with the guard counts of the last
        step."""
        values = {k: self._value(k) for k in self.settings}
        gains = {sensor: dr.exp(self.opt[k]) for sensor, k in self.gains.items()}
        self.flush(*values.values(), *gains.values())
        return ({k: parameters.flat(v) for k, v in values.items()},
                {sensor: np.array(g, dtype=np.float32) for sensor, g in gains.items()})

    def _gained(self, img, sensor: int):
        """render * gain of the sensor's reference (differentiable in the log gain)."""
        if sensor not in self.gains:
            return img
        gain = dr.exp(self.opt[self.gains[sensor]])
        channel = dr.arange(mi.UInt32, dr.width(img.array)) % 3
        return mi.TensorXf(img.array * dr.gather(mi.Float, gain, channel), img.shape)

    def flush(self, *also) -> None:
        """Evaluates the pending guard counts and gradients (and ``also``) and adds them to
        the counters and the gradient records."""
        grads = [g for stepped in self._stepped for g in stepped.values()]
        dr.eval(*also, *(count for _, count in self._pending), *grads)
        for counter, count in self._pending:
            setattr(self, counter, getattr(self, counter) + round(count[0]))
        keep = (self.config.iterations // 5 + 5) * len(self.references)  # what diagnosis reads
        for stepped in self._stepped:
            for key, g in stepped.items():
                kept = self.gradients.setdefault(key, [])
                kept.append(np.array(g, dtype=np.float64))
                del kept[:-keep]
        self._pending.clear()
        self._stepped.clear()

    @staticmethod
    def _true(mask) -> mi.Float:
        """How many components of ``mask`` are true, as a symbolic sum: no launch, no wait."""
        return dr.sum(dr.select(dr.ravel(mask), 1.0, 0.0), axis=None, mode="symbolic")

    def _sensor_images(self, i: int, n: int, sensor: int, draw: int = 0,
                       spp: int | None = None) -> list:
        """The renders the loss compares (times the gain, clamped when asked); ``draw`` picks
        another set of samples for the iteration."""
        renders = self.loss.renders
        slots = len(self.references) * renders
        images = []
        for b in range(renders):
            img = mi.render(self.scene, self.params, sensor=sensor, spp=spp or self.spp,
                            integrator=self.integrator,
                            seed=(_seed(self.config.seed, i, n * renders + b, slots) + draw)
                            % 2**32)
            img = self._gained(img[..., :3] if img.shape[2] > 3 else img, sensor)
            images.append(dr.clip(img, 0.0, 1.0) if self.config.clamp else img)
        return images

    def _image_loss(self, images: list, ref: Reference):
        target = dr.clip(ref.image, 0.0, 1.0) if self.config.clamp else ref.image
        return self.loss.fn(images, target, ref.weight)

    def _sensor_loss(self, i: int, n: int, sensor: int, ref: Reference):
        images = self._sensor_images(i, n, sensor)
        if self.differenced:  # the images the differences are taken around
            self._images[sensor] = [dr.detach(img) for img in images]
        return self._image_loss(images, ref)

    def _start_gains(self) -> None:
        """Each gain starts at the ratio of the means of reference and initial render, per
        channel (masked pixels out): from 1, a photograph several stops off would first drag
        the reflectances to their bounds while the gain catches up."""
        for sensor, key in self.gains.items():
            ref = self.references[sensor]
            w = ref.mask()
            img = self.render(self.initial, sensor, self.spp)
            rendered = np.sum(w * img, axis=(0, 1))
            wanted = np.sum(w * np.asarray(ref.image), axis=(0, 1))
            ratio = np.where(rendered > 0, wanted / np.maximum(rendered, 1e-30), 1.0)
            start = np.log(np.clip(ratio, math.exp(-GAIN_LIMIT), math.exp(GAIN_LIMIT)))
            self.opt[key] = mi.Float(start.astype(np.float32))

    def step(self) -> Step:
        start = time.perf_counter()
        i, c = self.iteration, self.config
        self._refine(i)
        if i == 0 and self.gains:
            self._start_gains()
        last = i + 1 >= c.iterations
        self._theta = None  # theta_i, read once the first render has evaluated it
        self._judged = None  # the windowed loss of this iteration, once known
        if c.step_per_sensor and len(self.references) > 1:
            loss = self._step_per_sensor(i, last)
        else:
            total = 0
            for n, (sensor, ref) in enumerate(self.references.items()):
                total += self._sensor_loss(i, n, sensor, ref)
            total /= len(self.references)
            loss = float(total.array[0])
            if not (last or self._reached(loss)):
                self._descend(total + self._smoothness_term(), loss, i,
                              list(enumerate(self.references)))
        theta, gains = self._read_theta()
        for key, v in theta.items():
            if v.size > SMALL:
                self.means.setdefault(key, []).append(float(np.mean(v)))
        judged = self._judge(loss)
        if judged is not None and judged < self.best.loss:
            self.best = Best(i, judged, theta, gains)
        self.last = Best(i, loss, theta, gains)
        reached = self._reached(loss)
        self.iteration = i + 1
        self.elapsed += time.perf_counter() - start
        out = Step(i, loss, theta, last or reached,
                   "min_error" if reached else "iterations" if last else "",
                   {k: parameter_error(theta[k], t, c.channels.get(k, 0))
                    for k, t in c.truth.items() if k in theta},
                   gains=gains)
        if c.image_error_every and (i % c.image_error_every == 0 or out.done):
            out.image_error = self.image_error(theta, gains)  # off the clock
        return out

    def _judge(self, loss: float) -> float | None:
        """The loss that decisions use: the mean of the last ``window`` losses, once there are
        that many. A single dual-buffer estimate is unbiased but noisy and can be < 0; taking
        its minimum, or stopping on it, would pick a lucky draw rather than good parameters."""
        if self._judged is None:
            if math.isfinite(loss):
                self.recent = (self.recent + [loss])[-self.loss.window:]
            full = len(self.recent) == self.loss.window and math.isfinite(loss)
            self._judged = sum(self.recent) / len(self.recent) if full else math.nan
        return None if math.isnan(self._judged) else self._judged

    def _reached(self, loss: float) -> bool:
        judged = self._judge(loss)
        return judged is not None and judged < self.config.min_error

    def _step_per_sensor(self, i: int, last: bool) -> float:
        losses = []
        for n, (sensor, ref) in enumerate(self.references.items()):
            total = self._sensor_loss(i, n, sensor, ref)
            losses.append(float(total.array[0]))
            if not last:
                self._descend(total + self._smoothness_term() / len(self.references),
                              losses[-1], i, [(n, sensor)])
        return float(np.mean(losses))

    def _smoothness_term(self):
        """sum_k w_k * mean_(a,b neighbours) (v_a - v_b)^2 over the textures and grids given a
        weight, at their current level: it damps the texel-to-texel noise of texels that few
        pixels see, while the image decides the pattern's low frequencies. It steers the
        gradient only; the recorded loss is the image's."""
        term = 0.0
        for key, weight in self.smooth.items():
            u = self.opt[key]
            level = self.level.get(key, 0)
            if (key, level) not in self._pairs:
                a, b = multires.neighbours(tuple(int(n) for n in u.shape))
                self._pairs[key, level] = (mi.UInt32(a), mi.UInt32(b))
            a, b = self._pairs[key, level]
            v = dr.exp(u.array) if self.settings[key].log else u.array
            diff = dr.gather(mi.Float, v, a) - dr.gather(mi.Float, v, b)
            term += weight * dr.mean(dr.square(diff), axis=None)
        return term

    def _read_theta(self) -> tuple[dict[str, np.ndarray], dict[int, np.ndarray]]:
        """theta_i and its gains, before the first step changes it. Read after the loss, not
        before the render: reading syncs, and by then the render has evaluated the values (a
        log parameter's e^u is recomputed in the one launch that also counts the guards)."""
        if self._theta is None:
            self._theta = self.theta()
        return self._theta

    def _descend(self, total, loss: float, i: int, sensors: list[tuple[int, int]]) -> None:
        """One Adam step from the gradient of ``total``, the loss of ``sensors`` ((slot,
        sensor) pairs)."""
        self._read_theta()
        if not math.isfinite(loss):
            self.skipped_steps += 1
            return
        self._schedule(i)
        dr.backward(total)
        self._difference_gradients(i, sensors)
        self._sanitize_gradients()
        self._stepped.append({k: dr.grad(self.opt[k]) for k in self.rates
                              if dr.width(self.opt[k]) <= SMALL})
        self.opt.step()
        for key in self.gains.values():
            self.opt[key] = dr.clip(self.opt[key], -GAIN_LIMIT, GAIN_LIMIT)
        for key, s in self.settings.items():
            value = self.opt[key]
            if s.log:
                lo, hi = s.latent_bounds()
                if lo > -LATENT_LIMIT or hi < LATENT_LIMIT:
                    self._pending.append(("clamped", self._true((value < lo) | (value > hi))))
                self.opt[key] = dr.clip(value, lo, hi)
                continue
            self._pending.append(("clamped", self._true((value < s.lo) | (value > s.hi))))
            self.opt[key] = dr.clip(value, s.lo, s.hi)
        self._apply()

    def _difference_gradients(self, i: int, sensors: list[tuple[int, int]]) -> None:
        """dL/d(eta) for each dielectric eta from a central difference of the images, in place
        of the AD gradient:

            D = (I(eta + h) - I(eta - h)) / 2h         (both sides from the same samples)
            dL/d(eta) ~ (L(I + h D) - L(I - h D)) / 2h  (I: this iteration's own renders)

        prb and prbvolpath sample the refracted direction detached from eta, so their gradient
        of eta holds only the Fresnel weights, not where the refracted rays go. On the Table 3
        kind (glass at the roughness floor, 64 px, 16 spp) its sign was random at every eta
        from 1.40 to 1.70; the difference's was right at each. The difference of the losses
        themselves would also follow the render noise's variance, which changes with eta
        (on a rough principled object it ended at eta 1.45 for a truth of 1.49); I is
        independent of D's samples, as Mitsuba's adjoint pass is of its primal pass. It costs
        two primal renders at a quarter of the spp per eta and sensor.
        """
        theta = self._theta[0]
        draw = 0x9E3779B9  # samples of their own, shared by both sides
        for key, widths in self.differenced.items():
            if not parameters.near_specular(widths, theta):
                continue  # the AD gradient stands
            s = self.settings[key]
            v = float(theta[key][0])
            lo, hi = max(v - ETA_STEP, s.lo), min(v + ETA_STEP, s.hi)
            if not hi > lo:
                continue
            sides = []
            for side in (lo, hi):
                with self.holding({key: np.array([side])}), dr.suspend_grad():
                    sides.append({sensor: self._sensor_images(
                        i, n, sensor, draw, max(1, self.spp // DIFFERENCE_SPP_DIVISOR))
                        for n, sensor in sensors})
            slope = 0.0
            with dr.suspend_grad():
                for _, sensor in sensors:
                    d = [(b - a) * (ETA_STEP / (hi - lo))
                         for a, b in zip(sides[0][sensor], sides[1][sensor])]
                    ref = self.references[sensor]
                    up = self._image_loss([x + y for x, y in zip(self._images[sensor], d)], ref)
                    down = self._image_loss([x - y for x, y in zip(self._images[sensor], d)], ref)
                    slope += float((up - down).array[0]) / (2 * ETA_STEP)
            dr.set_grad(self.opt[key], mi.Float(slope / len(sensors)))

    def _schedule(self, i: int) -> None:
        if self.config.cosine and self.config.iterations >= 2:
            f = rate_factor(i, self.config.iterations, True)
            self.opt.set_learning_rate({k: rate * f for k, rate in self.rates.items()})

    def _sanitize_gradients(self) -> None:
        bad = 0
        for key in self.rates:
            value = self.opt[key]
            grad = dr.grad(value)
            finite = dr.isfinite(grad)
            dr.set_grad(value, dr.select(finite, grad, 0))
            bad += self._true(~finite)
        self._pending.append(("nonfinite_steps", dr.select(bad > 0, 1.0, 0.0)))

    # -- renders off the clock --------------------------------------------------------------

    @contextlib.contextmanager
    def holding(self, values: dict[str, np.ndarray]):
        """The scene with the selected parameters set to ``values``, restored afterwards."""
        for key, v in values.items():
            self.params[key] = parameters.assign(self.params[key], v)
        self.params.update()
        try:
            yield self.scene
        finally:
            self._apply()

    def render(self, values: dict[str, np.ndarray], sensor: int, spp: int,
               gains: dict[int, np.ndarray] | None = None) -> np.ndarray:
        """A primal render with the selected parameters set to ``values``, times the sensor's
        gain when ``gains`` has one (as the loss compares it)."""
        with self.holding(values), dr.suspend_grad():
            img = mi.render(self.scene, self.params, sensor=sensor, spp=spp,
                            integrator=self.integrator, seed=_seed(self.config.seed, 0, 0, 1) + 7)
        img = np.array(img, dtype=np.float32)[..., :3]
        return img * gains[sensor] if gains and sensor in gains else img

    def image_error(self, values: dict[str, np.ndarray],
                    gains: dict[int, np.ndarray] | None = None) -> float:
        """RMSE of renders (times their gains) at ``image_error_spp`` against the references,
        each pixel by its mask weight, over all sensors; its time is not counted as
        optimizing time."""
        began = time.perf_counter()
        se = n = 0.0
        for sensor, ref in self.references.items():
            img = self.render(values, sensor, self.config.image_error_spp, gains)
            w = ref.mask()
            se += float(np.sum(w * (img - np.asarray(ref.image)) ** 2))
            n += float(np.sum(w))
        self.elapsed -= time.perf_counter() - began
        return math.sqrt(se / max(n, 1.0))

    # -- checkpoints ------------------------------------------------------------------------

    def checkpoint(self) -> bytes:
        """Everything needed to continue exactly, on any worker: values, Adam's moments and
        step counts, the best and the last iteration, the recent losses that dual-buffer's
        window averages, counters and the clock. The next iteration then renders the same
        parameters with the same seed as it would have without the interruption. The last
        step is evaluated here if no iteration has yet: its time goes on the job's clock."""
        began = time.perf_counter()
        self.flush()
        self.elapsed += time.perf_counter() - began
        arrays: dict[str, np.ndarray] = {
            "meta": np.array([self.iteration, self.elapsed, self.best.iteration, self.best.loss,
                              self.nonfinite_steps, self.skipped_steps, self.clamped,
                              self.last.iteration, self.last.loss], dtype=np.float64),
            "recent": np.array(self.recent, dtype=np.float64)}
        for n, key in enumerate(self.rates):
            value, _, _, (t, m, v, _) = self.opt.state[key]
            arrays[f"value{n}"] = parameters.flat(value)
            arrays[f"level{n}"] = np.array([self.level.get(key, -1)], dtype=np.int32)
            arrays[f"t{n}"] = np.asarray(t, dtype=np.uint32)
            arrays[f"m{n}"] = np.asarray(m, dtype=np.float32)
            arrays[f"v{n}"] = np.asarray(v, dtype=np.float32)
            for prefix, kept in (("best", self.best), ("last", self.last)):
                held = self._kept(kept)
                if key in held:
                    arrays[f"{prefix}{n}"] = held[key]
        buf = io.BytesIO()
        np.savez(buf, keys=np.array(list(self.rates)), **arrays)
        return buf.getvalue()

    def _kept(self, kept: Best) -> dict[str, np.ndarray]:
        """A kept iteration's values and gains, by Adam key."""
        return {**kept.values, **{self.gains[s]: g for s, g in kept.gains.items()
                                  if s in self.gains}}

    def restore(self, data: bytes) -> None:
        z = np.load(io.BytesIO(data), allow_pickle=False)
        if list(z["keys"]) != list(self.rates):
            raise ValueError("checkpoint holds other parameters (or exposure gains) than the job")
        (it, elapsed, best_it, best_loss, nonfinite, skipped, clamped, last_it,
         last_loss) = z["meta"].tolist()
        self.iteration, self.elapsed = int(it), float(elapsed)
        self.nonfinite_steps, self.skipped_steps = int(nonfinite), int(skipped)
        self.clamped = int(clamped)
        self.recent = z["recent"].tolist()
        kept: dict[str, dict[str, np.ndarray]] = {"best": {}, "last": {}}
        for n, key in enumerate(self.rates):
            if key in self.levels:
                self._set_level(key, int(z[f"level{n}"][0]), z[f"value{n}"])
            elif key in self.settings:
                self.opt[key] = parameters.assign(self.params[key], z[f"value{n}"])
            else:  # an exposure gain
                self.opt[key] = mi.Float(z[f"value{n}"])
            value, promoted, lr, (t, m, v, vmax) = self.opt.state[key]
            self.opt.state[key] = (value, promoted, lr,
                                   (type(t)(z[f"t{n}"]), type(m)(z[f"m{n}"]),
                                    type(v)(z[f"v{n}"]), vmax))
            for prefix in kept:
                if f"{prefix}{n}" in z:
                    kept[prefix][key] = z[f"{prefix}{n}"]
        by_key = {k: sensor for sensor, k in self.gains.items()}

        def best(iteration, loss, held: dict[str, np.ndarray]) -> Best:
            if not held:
                return Best()
            return Best(int(iteration), float(loss),
                        {k: v for k, v in held.items() if k in self.settings},
                        {by_key[k]: v for k, v in held.items() if k in by_key})

        self.best = best(best_it, best_loss, kept["best"])
        self.last = best(last_it, last_loss, kept["last"])
        self._apply()
