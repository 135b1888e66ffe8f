"""One optimization: Adam on the selected parameters, one iteration at a time, so that the
scheduler can interleave jobs, pause them and checkpoint them between iterations.

An iteration i renders every sensor that has a reference with the parameters theta_i, takes
the loss L_i (mean over those sensors), records (i, L_i, theta_i), and then, unless this was
the last iteration or L_i < min_error, back-propagates and steps to theta_{i+1}. So the best
iteration's parameters are exactly the ones that produced its loss, and no step is taken whose
result would never be rendered.

Guards (Dr.Jit 1.5's dr.clip propagates NaN, and Adam has no NaN guard of its own):
- a gradient component that is NaN/Inf is set to 0 before the step; with ``mask_updates``
  Adam then leaves that component and its moments alone. Counted in ``nonfinite_steps``.
- a loss that is NaN/Inf skips the step entirely. Counted in ``skipped_steps``.
- after the step each parameter is clipped into its [min, max].
"""

from __future__ import annotations

import io
import math
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from . import parameters
from .integrator import choose
from .losses import LOSSES


@dataclass
class Setting:
    """One selected parameter, with everything defaulted and validated by the caller."""

    key: str
    learning_rate: float
    lo: float
    hi: float
    initial: np.ndarray | None  # None: the scene's value


@dataclass
class Step:
    iteration: int
    loss: float
    values: dict[str, np.ndarray]  # theta_i (all selected parameters)
    done: bool
    stop_reason: str = ""


@dataclass
class Best:
    iteration: int = -1
    loss: float = math.inf
    values: dict[str, np.ndarray] = field(default_factory=dict)


def _seed(base: int, iteration: int, slot: int, slots: int) -> int:
    return (base * 1_000_003 + iteration * slots + slot) % 2**32


class Optimization:
    def __init__(self, scene: mi.Scene, settings: list[Setting],
                 references: dict[int, mi.TensorXf], *, loss: int, iterations: int,
                 min_error: float, spp: int, seed: int, cosine: bool = True) -> None:
        self.scene = scene
        self.settings = {s.key: s for s in settings}
        self.references = dict(sorted(references.items()))
        self.loss = LOSSES[loss]
        self.iterations, self.min_error, self.spp, self.seed = iterations, min_error, spp, seed
        self.cosine = cosine
        self.integrator, self.integrator_name, self.integrator_reason = choose(
            scene, list(self.settings))

        self.params = mi.traverse(scene)
        self.scene_values = {k: parameters.flat(self.params[k]) for k in self.settings}
        self.params.keep(list(self.settings))
        self.opt = mi.ad.Adam(lr=parameters.DEFAULT_LEARNING_RATE, mask_updates=True)
        for key, s in self.settings.items():
            start = s.initial if s.initial is not None else self.scene_values[key]
            self.opt[key] = parameters.assign(self.params[key], np.clip(start, s.lo, s.hi))
            self.opt.set_learning_rate({key: s.learning_rate})
        self.params.update(self.opt)
        self.initial = self.values()

        self.iteration = 0          # the next iteration to run
        self.elapsed = 0.0          # optimizing seconds, excluding pauses and other jobs' turns
        self.best = Best()
        self.nonfinite_steps = 0
        self.skipped_steps = 0

    # -- the loop ---------------------------------------------------------------------------

    def values(self) -> dict[str, np.ndarray]:
        return {k: parameters.flat(self.opt[k]) for k in self.settings}

    def step(self) -> Step:
        start = time.perf_counter()
        i = self.iteration
        slots = len(self.references) * self.loss.renders
        total = 0
        for n, (sensor, ref) in enumerate(self.references.items()):
            images = [mi.render(self.scene, self.params, sensor=sensor, spp=self.spp,
                                integrator=self.integrator,
                                seed=_seed(self.seed, i, n * self.loss.renders + b, slots))
                      for b in range(self.loss.renders)]
            total += self.loss.fn([img[..., :3] if img.shape[2] > 3 else img
                                   for img in images], ref)
        total /= len(self.references)
        loss = float(total.array[0])
        theta = self.values()
        if math.isfinite(loss) and loss < self.best.loss:
            self.best = Best(i, loss, theta)

        last = i + 1 >= self.iterations
        reached = math.isfinite(loss) and loss < self.min_error
        if not (last or reached):
            if math.isfinite(loss):
                self._schedule(i)
                dr.backward(total)
                self._sanitize_gradients()
                self.opt.step()
                for key, s in self.settings.items():
                    self.opt[key] = dr.clip(self.opt[key], s.lo, s.hi)
                self.params.update(self.opt)
            else:
                self.skipped_steps += 1
        self.iteration = i + 1
        self.elapsed += time.perf_counter() - start
        reason = "min_error" if reached else "iterations" if last else ""
        return Step(i, loss, theta, bool(reason), reason)

    def _schedule(self, i: int) -> None:
        # lr_i = lr * (0.1 + 0.9 * (1 + cos(pi * i / (N - 1))) / 2)
        if not self.cosine or self.iterations < 2:
            return
        f = 0.1 + 0.45 * (1.0 + math.cos(math.pi * i / (self.iterations - 1)))
        self.opt.set_learning_rate({k: s.learning_rate * f for k, s in self.settings.items()})

    def _sanitize_gradients(self) -> None:
        bad_step = False
        for key in self.settings:
            value = self.opt[key]
            grad = dr.grad(value)
            finite = dr.isfinite(grad)
            if not dr.all(finite, axis=None):
                bad_step = True
                dr.set_grad(value, dr.select(finite, grad, 0))
        self.nonfinite_steps += bad_step

    # -- results ----------------------------------------------------------------------------

    def render(self, values: dict[str, np.ndarray], sensor: int, spp: int) -> np.ndarray:
        """A primal render with the selected parameters set to ``values`` (then restored)."""
        current = self.values()
        for key, v in values.items():
            self.params[key] = parameters.assign(self.params[key], v)
        self.params.update()
        try:
            with dr.suspend_grad():
                img = mi.render(self.scene, self.params, sensor=sensor, spp=spp,
                                integrator=self.integrator, seed=_seed(self.seed, 0, 0, 1) + 7)
            return np.array(img, dtype=np.float32)
        finally:
            for key, v in current.items():
                self.params[key] = parameters.assign(self.params[key], v)
            self.params.update(self.opt)

    # -- checkpoints ------------------------------------------------------------------------

    def checkpoint(self) -> bytes:
        """Everything needed to continue exactly: values, Adam's moments and step counts, the
        best iteration so far, counters and the clock."""
        arrays: dict[str, np.ndarray] = {
            "meta": np.array([self.iteration, self.elapsed, self.best.iteration, self.best.loss,
                              self.nonfinite_steps, self.skipped_steps], dtype=np.float64)}
        for n, key in enumerate(self.settings):
            value, _, _, (t, m, v, _) = self.opt.state[key]
            arrays[f"value{n}"] = parameters.flat(value)
            arrays[f"t{n}"] = np.asarray(t, dtype=np.uint32)
            arrays[f"m{n}"] = np.asarray(m, dtype=np.float32)
            arrays[f"v{n}"] = np.asarray(v, dtype=np.float32)
            if key in self.best.values:
                arrays[f"best{n}"] = self.best.values[key]
        buf = io.BytesIO()
        np.savez(buf, keys=np.array(list(self.settings)), **arrays)
        return buf.getvalue()

    def restore(self, data: bytes) -> None:
        z = np.load(io.BytesIO(data))
        if list(z["keys"]) != list(self.settings):
            raise ValueError("checkpoint holds other parameters than the job")
        it, elapsed, best_it, best_loss, nonfinite, skipped = z["meta"].tolist()
        self.iteration, self.elapsed = int(it), float(elapsed)
        self.nonfinite_steps, self.skipped_steps = int(nonfinite), int(skipped)
        best = {}
        for n, key in enumerate(self.settings):
            self.opt[key] = parameters.assign(self.params[key], z[f"value{n}"])
            value, promoted, lr, (t, m, v, vmax) = self.opt.state[key]
            self.opt.state[key] = (value, promoted, lr,
                                   (type(t)(z[f"t{n}"]), type(m)(z[f"m{n}"]),
                                    type(v)(z[f"v{n}"]), vmax))
            if f"best{n}" in z:
                best[key] = z[f"best{n}"]
        self.best = Best(int(best_it), float(best_loss), best) if best else Best()
        self.params.update(self.opt)
