"""The one optimization loop: Adam on the selected parameters, one iteration at a time, so that
the scheduler can interleave jobs, pause them and checkpoint them between iterations. Every
special case is a named choice (engine/choices) that declares its state and hooks into the
loop at fixed points; with every choice off this is Mitsuba's plain Adam loop.

An iteration i renders every sensor that has a reference with the parameters theta_i, takes
the loss L_i (mean over those sensors), records (i, L_i, theta_i), and then, unless this was
the last iteration or L_i < min_error, back-propagates and steps to theta_{i+1}:

    before_render(i)                                 choices: the next coarse level, ...
    L_i = mean_s loss(on_images(render_s(theta_i)), R_s)
    record (i, L_i, theta_i)
    backward(L_i + sum on_loss)                      choices: smoothness
    on_gradient(i)                                   choices: eta by differences, eta held
    g <- select(isfinite(g), g, 0)                   the guards
    u <- Adam(u, g);  after_step(i);  u <- clip(u, bounds)
    theta_{i+1} = decode(expand(u))                  choices: coarse to fine, log space, floor

So the best iteration's parameters are exactly the ones that produced its loss, and no step is
taken whose result would never be rendered. With ``step_per_sensor`` (the thesis tool's way)
each sensor's gradient is applied as soon as it is known; by default they accumulate.

Guards (Dr.Jit 1.5's dr.clip propagates NaN, and Adam has no NaN guard of its own):
- a gradient component that is NaN/Inf is set to 0 before the step; with ``mask_updates``
  Adam then leaves that component and its moments alone. Counted in ``nonfinite_steps``.
- a loss that is NaN/Inf skips the step entirely. Counted in ``skipped_steps``.
- after the step each variable is clipped into its bounds; components the step pushed out are
  counted in ``clamped``.
The guards never wait for the device: their counts are symbolic sums, evaluated with the next
iteration's parameter values in one launch. The plain loop syncs once per iteration (reading
the loss); so does this one, and Python traces the next render while the backward pass runs.

``Optimization`` runs past 300 lines and this module past 500 on purpose: the loop and the
state every choice hooks into read best in one place, as Mitsuba's ``common.py`` keeps its
one loop; the special cases themselves are in ``choices/``.
"""

from __future__ import annotations

import contextlib
import io
import math
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import engine_api as api
from ..engine_api import SMALL
from ..truth import ParameterError, parameter_error
from . import integrator, parameters
from .choices import Choice, build, overrides
from .diagnosis import Kept
from .losses import LOSSES

HOOKS = ("variable", "expand", "encode", "decode", "bounds", "kept", "begin", "before_render",
         "on_images", "on_loss", "on_gradient", "after_step")


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
class Step:
    iteration: int
    loss: float
    values: dict[str, np.ndarray]  # theta_i (all selected parameters)
    done: bool
    stop_reason: str = ""
    errors: dict[str, ParameterError] = field(default_factory=dict)
    image_error: float | None = None
    gains: dict[int, np.ndarray] = field(default_factory=dict)  # sensor -> RGB gain
    spp: int = 0                   # what its renders took


@dataclass
class Best:
    """An iteration and the parameters that produced its loss (the best so far, or the last)."""

    iteration: int = -1
    loss: float = math.inf
    values: dict[str, np.ndarray] = field(default_factory=dict)
    gains: dict[int, np.ndarray] = field(default_factory=dict)


def _seed(base: int, iteration: int, slot: int, slots: int) -> int:
    return (base * 1_000_003 + iteration * slots + slot) % 2**32


def schedule_factor(settings: api.JobSettings, i: int) -> float:
    """The share of each base rate at step i: a half cosine from 1 to a tenth over the job,
    lr_i = lr * (0.1 + 0.9 * (1 + cos(pi * i / (N - 1))) / 2), or 1 throughout (constant)."""
    n = settings.iterations
    if settings.schedule != "cosine" or n < 2:
        return 1.0
    return 0.1 + 0.45 * (1.0 + math.cos(math.pi * i / (n - 1)))


class Optimization:
    """A job's optimization. State, declared once here; the choices declare their own.

    scene, params     the scene and its traversal, kept to the selected keys
    parameters        the job's settings per key (settings.ParameterSetting), as given
    starts            the values v the variables start from (flat, in range)
    opt, rates        Adam over the variables u (and the choices' own, e.g. log gains), and
                      each variable's base rate; ``factor`` is the schedule's share this step
    bounds            per key, the range its u is clipped to after a step
    chosen            the integrator, why, and its max_depth (the depth choice may cut it)
    current, images   theta_i once read, and this iteration's renders (detached) when a
                      choice wants them; ``frozen``: keys whose step a choice zeroed
    """

    def __init__(self, scene: mi.Scene, settings: api.JobSettings,
                 references: dict[int, Reference], choices: list[Choice] | None = None,
                 checkpoint: bytes | None = None, initial: dict[str, np.ndarray] | None = None,
                 truth: dict[str, np.ndarray] | None = None) -> None:
        self.scene = scene
        self.settings = settings
        self.parameters = {p.key: p for p in settings.parameters}
        self.truth = truth or {}  # flat known values, for errors
        initial = initial or {}
        self.references = dict(sorted(references.items()))
        self.loss = LOSSES[settings.loss]
        self.spp = settings.spp
        self.chosen = integrator.choose(scene, list(self.parameters))
        self.integrator_name = self.chosen.name

        self.params = mi.traverse(scene)
        self.scene_values = {k: parameters.flat(self.params[k]) for k in self.parameters}
        self.starts = {k: np.clip(initial[k] if k in initial else self.scene_values[k],
                                  p.lo, p.hi) for k, p in self.parameters.items()}
        self.params.keep(list(self.parameters))
        self.opt = mi.ad.Adam(lr=parameters.DEFAULT_LEARNING_RATE, mask_updates=True)
        self.rates = {k: p.learning_rate for k, p in self.parameters.items()}
        self.factor = 1.0
        self.gains: dict[int, str] = {}  # sensor -> Adam key of its log gain (exposure_gains)
        self.current: dict[str, np.ndarray] = {}
        self.images: dict[int, list] = {}
        self.frozen: set[str] = set()
        self._pending: list[tuple[str, mi.Float]] = []  # guard counts not yet read
        # per step, the gradient each small parameter and gain stepped on (latent), read
        # with the next theta: whether the images steered a drift (diagnosis), how noisy
        # the steps were (uncertainty)
        self.gradients: dict[str, list[np.ndarray]] = {}
        self._stepped: list[dict[str, object]] = []
        # per key, the iterations whose step a choice held (eta_hold, eta_differences' sparse
        # steps): no step was taken, and the zeroed gradient is not the images' (recorded as NaN)
        self.held: dict[str, list[int]] = {}

        saved = _read(checkpoint)
        self.choices = choices if choices is not None else build(settings)
        for c in self.choices:
            began = time.perf_counter()
            c.setup(self, _choice_state(saved, c.name))
            c.setup_seconds += time.perf_counter() - began
        self.active = [c for c in self.choices if c.on and c.applies]
        self._hooks = {h: [c for c in self.active if overrides(c, h)] for h in HOOKS}
        self._wants_images = any(c.wants_images for c in self.active)
        for key in self.parameters:
            latent = self._encode(key, self.starts[key])
            made = [v for c in self._hooks["variable"] if (v := c.variable(key, latent))
                    is not None]
            self.opt[key] = made[0] if made else parameters.assign(self.params[key], latent)
            self.opt.set_learning_rate({key: self.rates[key]})
        self.bounds = {k: self._bounds(k) for k in self.parameters}
        self._apply()
        for c in self._hooks["begin"]:
            began = time.perf_counter()
            c.begin(self)
            c.setup_seconds += time.perf_counter() - began
        self.integrator = integrator.make(self.chosen)
        self.integrator_reason = self.chosen.reason()
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
        if saved is not None:
            self._restore(saved)

    # -- between the variables and the scene ------------------------------------------------

    def _encode(self, key: str, value: np.ndarray) -> np.ndarray:
        for c in reversed(self._hooks["encode"]):
            value = c.encode(key, value)
        return value

    def decoded(self, key: str, latent):
        """v from u at u's own shape (elementwise maps only)."""
        for c in self._hooks["decode"]:
            latent = c.decode(key, latent)
        return latent

    def _value(self, key: str):
        """The scene value of a parameter, differentiable in its variable."""
        u = self.opt[key]
        for c in self._hooks["expand"]:
            u = c.expand(key, u)
        return self.decoded(key, u)

    def _bounds(self, key: str) -> tuple[float, float]:
        p = self.parameters[key]
        lo, hi = p.lo, p.hi
        for c in self._hooks["bounds"]:
            lo, hi = c.bounds(key, lo, hi)
        return lo, hi

    @property
    def kept(self) -> dict[str, Kept]:
        """Per parameter, what the diagnosis reads: the range its value is kept in, its floor,
        whether it is stepped in log space."""
        out = {}
        for key, p in self.parameters.items():
            k = Kept(p.lo, p.hi)
            for c in self._hooks["kept"]:
                k = c.kept(key, k)
            out[key] = k
        return out

    def variable(self, key: str) -> np.ndarray:
        """theta_i's value of ``key`` in the space it is stepped in (from ``current``)."""
        return self._encode(key, self.current[key])

    def rate(self, key: str) -> float:
        """The rate of ``key`` at this step (its base rate times the schedule's share)."""
        return self.rates[key] * self.factor

    def _apply(self) -> None:
        for key in self.parameters:
            self.params[key] = self._value(key)
        self.params.update()

    def theta(self) -> tuple[dict[str, np.ndarray], dict[int, np.ndarray]]:
        """theta and the gains, read in one launch together with the guard counts of the last
        step."""
        values = {k: self._value(k) for k in self.parameters}
        gains = {sensor: dr.exp(self.opt[k]) for sensor, k in self.gains.items()}  # log g
        self.flush(*values.values(), *gains.values())
        return ({k: parameters.flat(v) for k, v in values.items()},
                {sensor: np.array(g, dtype=np.float32) for sensor, g in gains.items()})

    # -- the loop ---------------------------------------------------------------------------

    def _call(self, hook: str, *args) -> list:
        """``hook`` on every choice in force that has it, in order, each timed on its own."""
        out = []
        for c in self._hooks[hook]:
            began = time.perf_counter()
            out.append(getattr(c, hook)(self, *args))
            c.seconds += time.perf_counter() - began
        return out

    def step(self) -> Step:
        start = time.perf_counter()
        i, s = self.iteration, self.settings
        self.spp = s.spp_at(i)
        if any(self._call("before_render", i)):
            self._apply()
        last = i + 1 >= s.iterations
        self._theta = None  # theta_i, read once the first render has evaluated it
        self._judged = None  # the windowed loss of this iteration, once known
        if s.sensor_mode == "step_per_sensor" and len(self.references) > 1:
            loss = self._step_per_sensor(i, last)
        else:
            total = 0
            for n, (sensor, ref) in enumerate(self.references.items()):
                total += self._sensor_loss(i, n, sensor, ref)
            total /= len(self.references)
            loss = float(total.array[0])
            if not (last or self._reached(loss)):
                self._descend(total + sum(self._call("on_loss")), loss, i,
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
                   {k: parameter_error(theta[k], t, self.channels(k))
                    for k, t in self.truth.items() if k in theta},
                   gains=gains, spp=self.spp)
        if s.image_error_every and (i % s.image_error_every == 0 or out.done):
            out.image_error = self.image_error(theta, gains)  # off the clock
        return out

    def channels(self, key: str) -> int:
        """A texture's or grid's channel count (its errors are per channel); 0 otherwise."""
        value = self.params[key]
        return int(value.shape[-1]) if dr.is_tensor_v(value) else 0

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
        return judged is not None and judged < self.settings.min_error

    def _step_per_sensor(self, i: int, last: bool) -> float:
        losses = []
        for n, (sensor, ref) in enumerate(self.references.items()):
            total = self._sensor_loss(i, n, sensor, ref)
            losses.append(float(total.array[0]))
            if not last:
                self._descend(total + sum(self._call("on_loss")) / len(self.references),
                              losses[-1], i, [(n, sensor)])
        return float(np.mean(losses))

    def _read_theta(self) -> tuple[dict[str, np.ndarray], dict[int, np.ndarray]]:
        """theta_i and its gains, before the first step changes it. Read after the loss, not
        before the render: reading syncs, and by then the render has evaluated the values (a
        log parameter's e^u is recomputed in the one launch that also counts the guards)."""
        if self._theta is None:
            self._theta = self.theta()
            self.current = self._theta[0]
        return self._theta

    def _descend(self, total, loss: float, i: int, sensors: list[tuple[int, int]]) -> None:
        """One Adam step from the gradient of ``total``, the loss of ``sensors`` ((slot,
        sensor) pairs)."""
        self._read_theta()
        if not math.isfinite(loss):
            self.skipped_steps += 1
            return
        self.factor = schedule_factor(self.settings, i)
        self.opt.set_learning_rate({k: self.rate(k) for k in self.rates})
        dr.backward(total)
        self.frozen.clear()
        self._call("on_gradient", i, sensors)
        self._sanitize_gradients()
        for key in self.frozen:
            self.held.setdefault(key, []).append(i)
        self._stepped.append({k: None if k in self.frozen else dr.grad(self.opt[k])
                              for k in self.rates if dr.width(self.opt[k]) <= SMALL})
        self.opt.step()
        self._call("after_step", i)
        for key, (lo, hi) in self.bounds.items():
            value = self.opt[key]
            self._pending.append(("clamped", self._true((value < lo) | (value > hi))))
            self.opt[key] = dr.clip(value, lo, hi)
        self._apply()

    def _sanitize_gradients(self) -> None:
        bad = 0
        for key in self.rates:
            value = self.opt[key]
            grad = dr.grad(value)
            finite = dr.isfinite(grad)
            dr.set_grad(value, dr.select(finite, grad, 0))
            bad += self._true(~finite)
        self._pending.append(("nonfinite_steps", dr.select(bad > 0, 1.0, 0.0)))

    def flush(self, *also) -> None:
        """Evaluates the pending guard counts and gradients (and ``also``) and adds them to
        the counters and the gradient records."""
        grads = [g for stepped in self._stepped for g in stepped.values() if g is not None]
        dr.eval(*also, *(count for _, count in self._pending), *grads)
        for counter, count in self._pending:
            setattr(self, counter, getattr(self, counter) + round(count[0]))
        keep = (self.settings.iterations // 5 + 5) * len(self.references)  # what diagnosis reads
        for stepped in self._stepped:
            for key, g in stepped.items():
                kept = self.gradients.setdefault(key, [])
                kept.append(np.full(dr.width(self.opt[key]), np.nan) if g is None
                            else np.array(g, dtype=np.float64))
                del kept[:-keep]
        self._pending.clear()
        self._stepped.clear()

    @staticmethod
    def _true(mask) -> mi.Float:
        """How many components of ``mask`` are true, as a symbolic sum: no launch, no wait."""
        return dr.sum(dr.select(dr.ravel(mask), 1.0, 0.0), axis=None, mode="symbolic")

    def sensor_images(self, i: int, n: int, sensor: int, draw: int = 0,
                      spp: int | None = None) -> list:
        """The renders the loss compares (as the choices make them: times the gain, ...);
        ``draw`` picks another set of samples for the iteration."""
        renders = self.loss.renders
        slots = len(self.references) * renders
        images = []
        for b in range(renders):
            img = mi.render(self.scene, self.params, sensor=sensor, spp=spp or self.spp,
                            integrator=self.integrator,
                            seed=(_seed(self.settings.seed, i, n * renders + b, slots) + draw)
                            % 2**32)
            images.append(img[..., :3] if img.shape[2] > 3 else img)
        for c in self._hooks["on_images"]:
            began = time.perf_counter()
            images = c.on_images(self, sensor, images)
            c.seconds += time.perf_counter() - began
        return images

    def image_loss(self, images: list, ref: Reference):
        """The loss of a sensor's renders against its reference (both clamped to [0, 1] when
        the job asks: an LDR comparison)."""
        target = ref.image
        if self.settings.clamp:
            images = [dr.clip(img, 0.0, 1.0) for img in images]
            target = dr.clip(target, 0.0, 1.0)
        return self.loss.fn(images, target, ref.weight)

    def _sensor_loss(self, i: int, n: int, sensor: int, ref: Reference):
        images = self.sensor_images(i, n, sensor)
        if self._wants_images:
            self.images[sensor] = [dr.detach(img) for img in images]
        return self.image_loss(images, ref)

    # -- what the job's status says of its choices ------------------------------------------

    def status(self) -> list[api.ChoiceStatus]:
        """The choices that concern the job, on or off, with their measured cost."""
        n = max(1, self.iteration)
        return [api.ChoiceStatus(c.name, c.on, c.why, c.seconds / n, c.setup_seconds,
                                 c.switchable) for c in self.choices if c.applies]

    def choice_notes(self) -> list[str]:
        """What the choices in force say per parameter, once, in the job's notes."""
        return [line for c in self.active for line in c.notes()]

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
                            integrator=self.integrator,
                            seed=_seed(self.settings.seed, 0, 0, 1) + 7)
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
            img = self.render(values, sensor, self.settings.image_error_spp, gains)
            w = ref.mask()
            se += float(np.sum(w * (img - np.asarray(ref.image)) ** 2))
            n += float(np.sum(w))
        self.elapsed -= time.perf_counter() - began
        return math.sqrt(se / max(n, 1.0))

    # -- checkpoints ------------------------------------------------------------------------

    def checkpoint(self) -> bytes:
        """Everything needed to continue exactly, on any worker: values, Adam's moments and
        step counts, the best and the last iteration, the recent losses that dual-buffer's
        window averages, counters and the clock, and each choice's state and cost. The next
        iteration then renders the same parameters with the same seed as it would have
        without the interruption. The last step is evaluated here if no iteration has yet:
        its time goes on the job's clock."""
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
            arrays[f"t{n}"] = np.asarray(t, dtype=np.uint32)
            arrays[f"m{n}"] = np.asarray(m, dtype=np.float32)
            arrays[f"v{n}"] = np.asarray(v, dtype=np.float32)
            arrays[f"held{n}"] = np.array(self.held.get(key, []), dtype=np.int64)
            for prefix, kept in (("best", self.best), ("last", self.last)):
                held = self._kept(kept)
                if key in held:
                    arrays[f"{prefix}{n}"] = held[key]
        for c in self.choices:
            arrays[f"cost:{c.name}"] = np.array([c.seconds, c.setup_seconds], np.float64)
            for name, value in c.state().items():
                arrays[f"choice:{c.name}:{name}"] = np.asarray(value)
        buf = io.BytesIO()
        np.savez(buf, keys=np.array(list(self.rates)), **arrays)
        return buf.getvalue()

    def _kept(self, kept: Best) -> dict[str, np.ndarray]:
        """A kept iteration's values and gains, by Adam key."""
        return {**kept.values, **{self.gains[s]: g for s, g in kept.gains.items()
                                  if s in self.gains}}

    def _restore(self, z) -> None:
        try:
            self._restore_arrays(z)
        except CheckpointError:
            raise
        except (ValueError, KeyError, OSError) as exc:
            raise CheckpointError(str(exc)) from None

    def _restore_arrays(self, z) -> None:
        if list(z["keys"]) != list(self.rates):
            raise CheckpointError("checkpoint holds other parameters (or exposure gains) than "
                                  "the job")
        (it, elapsed, best_it, best_loss, nonfinite, skipped, clamped, last_it,
         last_loss) = z["meta"].tolist()
        self.iteration, self.elapsed = int(it), float(elapsed)
        self.nonfinite_steps, self.skipped_steps = int(nonfinite), int(skipped)
        self.clamped = int(clamped)
        self.recent = z["recent"].tolist()
        for c in self.choices:
            if f"cost:{c.name}" in z:
                c.seconds, c.setup_seconds = z[f"cost:{c.name}"].tolist()
        kept: dict[str, dict[str, np.ndarray]] = {"best": {}, "last": {}}
        for n, key in enumerate(self.rates):
            # the variable's layout is the choices' (restored with their state at setup)
            self.opt[key] = parameters.assign(self.opt[key], z[f"value{n}"])
            value, promoted, lr, (t, m, v, vmax) = self.opt.state[key]
            self.opt.state[key] = (value, promoted, lr,
                                   (type(t)(z[f"t{n}"]), type(m)(z[f"m{n}"]),
                                    type(v)(z[f"v{n}"]), vmax))
            if f"held{n}" in z:  # (absent from checkpoints before it was kept)
                self.held[key] = z[f"held{n}"].tolist()
            for prefix in kept:
                if f"{prefix}{n}" in z:
                    kept[prefix][key] = z[f"{prefix}{n}"]
        by_key = {k: sensor for sensor, k in self.gains.items()}

        def best(iteration, loss, held: dict[str, np.ndarray]) -> Best:
            if not held:
                return Best()
            return Best(int(iteration), float(loss),
                        {k: v for k, v in held.items() if k in self.parameters},
                        {by_key[k]: v for k, v in held.items() if k in by_key})

        self.best = best(best_it, best_loss, kept["best"])
        self.last = best(last_it, last_loss, kept["last"])
        self._apply()


class CheckpointError(ValueError):
    """A checkpoint that does not restore this job (another job's, or damaged)."""


def _read(checkpoint: bytes | None):
    if checkpoint is None:
        return None
    try:
        return np.load(io.BytesIO(checkpoint), allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise CheckpointError(f"not a checkpoint ({exc})") from None


def _choice_state(z, name: str) -> dict[str, np.ndarray] | None:
    """A choice's state in a checkpoint (None: a fresh start; empty: it saved none)."""
    if z is None:
        return None
    prefix = f"choice:{name}:"
    return {k[len(prefix):]: z[k] for k in z.files if k.startswith(prefix)}
