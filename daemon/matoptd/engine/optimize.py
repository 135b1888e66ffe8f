"""The one optimization loop: Adam on the selected parameters, one iteration at a time, so that
the scheduler can interleave jobs, pause them and checkpoint them between iterations. Every
special case is a named choice (engine/choices) that declares its state and hooks into the
loop at fixed points; with every choice off this is Mitsuba's plain Adam loop.

An iteration i renders every sensor that has a reference with the parameters theta_i, takes
the loss L_i (mean over those sensors), records (i, L_i, theta_i), and then, unless this was
the last iteration or L_i < min_error, back-propagates and steps to theta_{i+1}:

    before_render(ctx)                               choices: the next coarse level, ...
    L_i = mean_s loss(on_images(render_s(theta_i)), R_s)
    record (i, L_i, theta_i)
    backward(L_i + sum on_loss)                      choices: smoothness
    on_gradient(ctx)                                 choices: eta by differences, eta held
    g <- select(isfinite(g), g, 0)                   the guards
    u <- Adam(u, g);  u <- clip(u, bounds)
    theta_{i+1} = decode(expand(u))                  choices: coarse to fine, log space, floor

So the best iteration's parameters are exactly the ones that produced its loss, and no step is
taken whose result would never be rendered. With ``step_per_sensor`` (the thesis tool's way)
each sensor's gradient is applied as soon as it is known; by default they accumulate.
With the ``frozen`` choice a sensor group's render, loss and backward pass are one recorded
function, replayed (engine/frozen.py): the same steps, without tracing them each iteration.

Guards (guards.py): a non-finite gradient component is zeroed before the step (counted in
``nonfinite_steps``), a NaN/Inf loss skips the step (``skipped_steps``), and each variable is
clipped into its bounds after it (``clamped``). The guards never wait for the device: their
counts are symbolic sums, evaluated with the next iteration's parameter values in one launch.
The plain loop syncs once per iteration (reading the loss); so does this one, and Python
traces the next render while the backward pass runs.

The state is plain data: a record per variable (records.py), the counters and kept iterations
(``Progress``), Adam's moments, and each choice's own; a checkpoint is all of it by name
(checkpoint.py).
"""

from __future__ import annotations

import math
import time
import weakref

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import engine_api as api
from ..engine_api import SMALL
from ..truth import parameter_error
from . import checkpoint as codec
from . import integrator, parameters
from .checkpoint import CheckpointError
from .choices import HOLD, Choice, build
from .context import Context
from .diagnosis import Kept
from .guards import Guards
from .hooks import Hooks
from .losses import LOSSES
from .maps import Maps
from .records import Best, ParamRecord, Progress, Step
from .renders import Reference, Renders

__all__ = ["Best", "CheckpointError", "Optimization", "Reference", "Step", "rate_share",
           "schedule_factor"]


def rate_share(settings: api.JobSettings, i: int, record: ParamRecord) -> float:
    """The share of ``record``'s step rate at step i: the schedule's from its own begin, or
    all of it for a record a choice keeps from decaying (medium_constant_rate)."""
    return schedule_factor(settings, i, record.schedule_begin) if record.decays else 1.0


def schedule_factor(settings: api.JobSettings, i: int, begin: int = 0) -> float:
    """The share of each base rate at step i: a half cosine from 1 to a tenth over the job's
    steps from ``begin`` (a variable's ``schedule_begin``) on, or 1 throughout (constant):

        lr_i = lr * (0.1 + 0.9 * (1 + cos(pi * (i - b) / (N - 1 - b))) / 2)
    """
    n = settings.iterations - begin
    if settings.schedule != "cosine" or n < 2:
        return 1.0
    return 0.1 + 0.45 * (1.0 + math.cos(math.pi * min(max(i - begin, 0), n - 1) / (n - 1)))


class Optimization:
    """A job's optimization: its records (one per variable), Adam over their u, the renders,
    the choices in force with the maps they contribute, and ``progress``."""

    def __init__(self, scene: mi.Scene, settings: api.JobSettings,
                 references: dict[int, Reference], choices: list[Choice] | None = None,
                 checkpoint: bytes | None = None, initial: dict[str, np.ndarray] | None = None,
                 truth: dict[str, np.ndarray] | None = None,
                 shelf: dict[str, object] | None = None) -> None:
        self.settings = settings
        # A kept scene's integrator and recordings (kept_scenes.Loaded.shelf), taken and left
        self.shelf = shelf if shelf is not None else {}
        self.loss = LOSSES[settings.loss]
        self.spp = settings.spp
        self.chosen = integrator.choose(scene, [p.key for p in settings.parameters])
        self.integrator_name = self.chosen.name
        params = mi.traverse(scene)
        self.records = _records(params, settings, initial or {}, truth or {})
        params.keep([k for k in self.records])
        # Its parts hold the loop weakly: a cycle would keep the job's AD graph alive until
        # Python's collector runs, which it may do inside a later job's AD traversal.
        me = weakref.proxy(self)
        self.renders = Renders(scene, params, dict(sorted(references.items())), settings,
                               self.loss, lambda s, images: me.hooks.on_images(s, images),
                               lambda: me._apply())
        self.ctx = Context(me)
        self.opt = mi.ad.Adam(lr=parameters.DEFAULT_LEARNING_RATE, mask_updates=True)
        self.progress = Progress()
        self.initial: dict[str, np.ndarray] = {}
        self.guards = Guards()
        self.said: list[str] = []  # notes said during the job (reported at its end)
        self.group = None  # a choice's stand-in for the renders and backward pass (frozen)
        self.parked = False  # the scene's parameters detached until the next step (park)
        saved = codec.loads(checkpoint) if checkpoint is not None else None

        self.hooks = Hooks(self.ctx, choices if choices is not None else build(settings),
                           self.records, None if saved is None else
                           {name: c.state for name, c in saved.choices.items()})
        self.choices, self.active = self.hooks.choices, self.hooks.active
        self.maps = Maps(self.active)
        self.opt.uniform = any(c.adam_uniform for c in self.active)
        self.opt.beta_1 = min([c.adam_beta_1 for c in self.active if c.adam_beta_1 is not None],
                              default=self.opt.beta_1)
        for key, r in self.records.items():
            latent = self.maps.encode(key, r.start)
            made = self.maps.variable(key, latent)
            self.opt[key] = made if made is not None else (
                mi.Float(latent) if r.scene is None else parameters.assign(params[key], latent))
            self.opt.set_learning_rate({key: r.rate})
            r.bounds, r.step_rate = self.maps.bounds(r), self.maps.rate(r)
        self._apply()
        begun = self.hooks.begin()
        if begun is not None:
            self.chosen.max_depth, self.chosen.depth_origin = begun.max_depth, begun.origin
        self.renders.integrator = integrator.make(self.chosen, shelf=self.shelf)
        self.integrator_reason = self.chosen.reason()
        self.group = next(filter(None, (c.group_loss(self.ctx) for c in self.active)), None)
        if self.group is not None:
            self._apply()  # the scene's values as the group's leaves
            self.renders.frozen = self.group.render
        self.initial = self.theta()[0]
        if saved is not None:
            self._restore(saved)

    # -- between the variables and the scene ------------------------------------------------

    def _value(self, key: str):
        """The value of a variable, differentiable in its u."""
        return self.maps.decode(key, self.maps.expand(key, self.opt[key]))

    @property
    def parameters(self) -> dict[str, ParamRecord]:  # not the choices' own variables (gains)
        return {k: r for k, r in self.records.items() if r.scene is not None}

    @property
    def kept(self) -> dict[str, Kept]:
        """Per parameter, what the diagnosis reads: the range its value is kept in, its floor,
        whether it is stepped in log space."""
        return {k: self.maps.kept(r) for k, r in self.parameters.items()}

    def rate(self, key: str) -> float:
        """The rate of ``key`` at this step (its step rate times the schedule's share)."""
        r = self.records[key]
        return r.step_rate * rate_share(self.settings, self.ctx.iteration, r)

    def _apply(self) -> None:
        params = self.renders.params
        for key in self.parameters:
            value = self._value(key)
            params[key] = value if self.group is None else self.group.leaf(key, value)
        params.update()

    def park(self) -> None:
        """The scene's parameters detached until the next step, while another run shares the
        process (a standard-error estimate beside a loaded job): Mitsuba dispatches a BSDF's
        virtual call over every live instance, this scene's too, and that run's forward-mode
        passes refuse the AD edges this scene holds (an eta's to the 1/eta its plugin keeps)."""
        params = self.renders.params
        for key in self.parameters:
            params[key] = dr.detach(params[key])
        params.update()
        self.parked = True

    def theta(self) -> tuple[dict[str, np.ndarray], dict[int, np.ndarray]]:
        """theta and the gains, read in one launch together with the guard counts of the last
        step."""
        values = {k: self._value(k) for k in self.records}
        self.flush(*values.values())
        flat = {k: parameters.flat(v) for k, v in values.items()}
        return ({k: v for k, v in flat.items() if self.records[k].scene is not None},
                {r.sensor: flat[k] for k, r in self.records.items() if r.is_gain})

    # -- the loop ---------------------------------------------------------------------------

    def step(self) -> Step:
        start = time.perf_counter()
        p, s = self.progress, self.settings
        i = self.ctx.iteration = p.iteration
        self.spp = s.spp_at(i)
        for r in self.records.values():
            r.step_rate = self.maps.rate(r)
        changed = {k: v for out in self.hooks.call("before_render") for k, v in out.items()}
        for key, variable in changed.items():
            self.opt[key] = variable
            self.opt.set_learning_rate({key: self.records[key].step_rate})
        if self.parked or any(self.records[k].scene is not None for k in changed):
            self._apply()
            self.parked = False
        last = i + 1 >= s.iterations
        self._theta = None  # theta_i, read once the first render has evaluated it
        self._judged = None  # the windowed loss of this iteration, once known
        refs = self.renders.references
        if s.sensor_mode == "step_per_sensor" and len(refs) > 1:
            losses = []
            for n, sensor in enumerate(refs):
                total = self._loss(i, [(n, sensor)], 1)
                losses.append(float(total.array[0]))
                if not last:
                    self._descend(total, sum(self.hooks.call("on_loss")) / len(refs), losses[-1],
                                  i, [(n, sensor)])
            loss = float(np.mean(losses))
        else:
            total = self._loss(i, list(enumerate(refs)), len(refs))
            loss = float(total.array[0])
            if not (last or self._reached(loss)):
                self._descend(total, sum(self.hooks.call("on_loss")), loss, i,
                              list(enumerate(refs)))
        theta, gains = self._read_theta()
        for key, v in theta.items():
            if v.size > SMALL:
                self.records[key].means.append(float(np.mean(v)))
        judged = self._judge(loss)
        if judged is not None and judged < p.best.loss:
            p.best = Best(i, judged, theta, gains)
        p.last = Best(i, loss, theta, gains)
        reached = self._reached(loss)
        p.iteration = i + 1
        p.elapsed += time.perf_counter() - start
        out = Step(i, loss, theta, last or reached,
                   "min_error" if reached else "iterations" if last else "",
                   {k: parameter_error(theta[k], r.truth, r.channels)
                    for k, r in self.parameters.items() if r.truth is not None},
                   gains=gains, spp=self.spp)
        if s.image_error_every and (i % s.image_error_every == 0 or out.done):
            began, out.image_error = time.perf_counter(), self.renders.image_error(theta, gains)
            p.elapsed -= time.perf_counter() - began  # off the clock
        return out

    def _judge(self, loss: float) -> float | None:
        """The loss that decisions use: the mean of the last ``window`` losses, once there are
        that many. A single dual-buffer estimate is unbiased but noisy and can be < 0; taking
        its minimum, or stopping on it, would pick a lucky draw rather than good parameters."""
        if self._judged is None:
            p = self.progress
            if math.isfinite(loss):
                p.recent = (p.recent + [loss])[-self.loss.window:]
            full = len(p.recent) == self.loss.window and math.isfinite(loss)
            self._judged = sum(p.recent) / len(p.recent) if full else math.nan
        return None if math.isnan(self._judged) else self._judged

    def _reached(self, loss: float) -> bool:
        judged = self._judge(loss)
        return judged is not None and judged < self.settings.min_error

    def _read_theta(self) -> tuple[dict[str, np.ndarray], dict[int, np.ndarray]]:
        """theta_i and its gains, before the first step changes it. Read after the loss, not
        before the render: reading syncs, and by then the render has evaluated the values (a
        log parameter's e^u is recomputed in the one launch that also counts the guards)."""
        if self._theta is None:
            self._theta = self.theta()
            values, gains = self._theta
            for key, r in self.records.items():
                r.current = gains[r.sensor] if r.is_gain else values[key]
        return self._theta

    def _loss(self, i: int, group: list[tuple[int, int]], divisor: int):
        """The loss of ``group`` ((slot, sensor) pairs) over ``divisor``; frozen, with its
        backward pass begun, where a choice stands in (``group``)."""
        if self.group is not None:
            return self.group(group, divisor)
        return sum(self._sensor_loss(i, n, sensor) for n, sensor in group) / divisor

    def _sensor_loss(self, i: int, n: int, sensor: int):
        images = self.renders.sensor_images(i, n, sensor, 0, self.spp)
        if self.hooks.wants_images:
            self.ctx.images[sensor] = [dr.detach(img) for img in images]
        return self.renders.image_loss(images, self.renders.references[sensor])

    def _descend(self, total, extra, loss: float, i: int, sensors: list[tuple[int, int]]
                 ) -> None:
        """One Adam step from the gradient of ``total`` + ``extra`` (the choices' terms),
        ``total`` the loss of ``sensors`` ((slot, sensor) pairs)."""
        self._read_theta()
        if not math.isfinite(loss):
            self.progress.skipped_steps += 1
            return
        self.opt.set_learning_rate({k: self.rate(k) for k in self.records})
        self.group.backward(extra) if self.group else dr.backward(total + extra)
        ctx = self.ctx
        ctx.sensors, ctx.held = sensors, set()
        for c in self.hooks.by_hook["on_gradient"]:
            for key, grad in self.hooks.timed(c, "seconds", c.on_gradient, ctx).items():
                dr.set_grad(self.opt[key], 0.0 if grad is HOLD else grad)
                if grad is HOLD:
                    ctx.held.add(key)
        self.guards.sanitize(self.opt, self.records, ctx.held)
        for key in ctx.held:
            self.records[key].held.append(i)
        self.opt.step()
        _uncount(self.opt, ctx.held)
        self.guards.clip(self.opt, self.records)
        self._apply()

    def flush(self, *also) -> None:
        """Evaluates what the guards count and keep (and ``also``)."""
        self.guards.flush(self.progress, self.records,
                          (self.settings.iterations // 5 + 5) * len(self.renders.references),
                          also)

    def status(self) -> list[api.ChoiceStatus]:
        return self.hooks.status(self.progress.iteration)

    # -- checkpoints ------------------------------------------------------------------------

    def checkpoint(self) -> bytes:
        """Everything needed to continue exactly, on any worker (checkpoint.py). The next
        iteration then renders the same parameters with the same seed as it would have
        without the interruption. The last step is evaluated here if no iteration has yet:
        its time goes on the job's clock."""
        began = time.perf_counter()
        self.flush()
        self.progress.elapsed += time.perf_counter() - began
        return codec.dumps(codec.save(self.opt, self.records, self.choices, self.progress))

    def _restore(self, saved: codec.Checkpoint) -> None:
        self.progress = codec.restore(saved, self.opt, self.records, self.choices)
        for r in self.records.values():
            r.step_rate = self.maps.rate(r)  # from theta_{i-1}, as if never interrupted
        self._apply()


def _records(params: mi.SceneParameters, settings: api.JobSettings,
             initial: dict[str, np.ndarray], truth: dict[str, np.ndarray]
             ) -> dict[str, ParamRecord]:
    """A record per selected parameter, its start the value given (else the scene's) in range."""
    out = {}
    for p in settings.parameters:
        value = params[p.key]
        scene = parameters.flat(value)
        kind_shape = parameters.kind_and_shape(p.key, value)
        tensor = dr.is_tensor_v(value)
        out[p.key] = ParamRecord(
            p.key, kind_shape[0] if kind_shape else "vector", p.lo, p.hi, p.learning_rate,
            np.clip(initial[p.key] if p.key in initial else scene, p.lo, p.hi), scene,
            initial_given=p.initial is not None, rate_given=p.rate_given,
            smoothness=p.smoothness,
            channels=int(value.shape[-1]) if tensor else 0,
            shape=tuple(int(n) for n in value.shape) if tensor else (),
            truth=truth.get(p.key))
    return out


def _uncount(opt: mi.ad.Adam, held: set[str]) -> None:
    """A held step is no step: Adam's count t goes back to what it was. Dr.Jit's mask leaves a
    zero-gradient parameter's m and v alone but counts t, and the debiasing
    sqrt(1 - b2^t) / (1 - b1^t) then reads k real steps as t: after a hold of n iterations
    the steps run at up to sqrt((n + k) / k) times the rate (eta after its hold: 1.4-7x)."""
    for key in held:
        value, promoted, lr, (t, *moments) = opt.state[key]
        opt.state[key] = (value, promoted, lr, (t - 1, *moments))
