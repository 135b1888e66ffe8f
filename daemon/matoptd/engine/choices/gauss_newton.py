"""A job's scalars and colours stepped by damped Gauss-Newton (Levenberg-Marquardt) in a trust
region, in place of Adam and its heuristics; textures, grids and vertices keep Adam in the
same iterations.

Adam's steps are the rate's, whatever the curvature: on the thesis's Table 4 scene (a rough
dielectric around a homogeneous medium) a parameter the images barely constrain and one they
constrain tightly move alike, so eta runs ahead of a black medium (eta_hold) and later crawls
back. The standard errors already estimate J for every scalar and colour component twice from
independent samples (jacobian.py); from them H = 2 J^T C J (only products across the two
estimates, so J's own noise does not inflate it) and g = 2 J^T C (I - R) are unbiased, and
the step H^-1 g takes each direction as far as the images say (trust_region.py).

Every EVERY-th iteration, before it renders, J is estimated at the current values (its own
samples, at the job's spp, in one round: the same on any machine) and a step proposed, at
most ``radius`` difference steps long. At the next step the fall of the loss along it is
read from the gradients at both ends (the trapezoid rule, exact for a quadratic), which the
next estimate makes anyway: a fall beyond its noise keeps the step and grows the radius, a
rise undoes it and shrinks the radius (the next step is then taken from the start's estimate).
The losses the loop renders would judge it with far more noise: on a 32 px Cornell box at
4 spp, successive losses varied by a factor of 5 while the model's predicted falls were a
tenth of that. A direction the images do not resolve (J^T J's eigenvalue within its noise) is
damped to what its noise vouches for; the status names its component. Only for a handful of
components (J costs a pass per parameter, a colour's three in one) and a least-squares loss.

Measured on the thesis's scenes (bench/real_scenes.py --with-choice gauss_newton=on, 64x48,
60 iterations, 16 spp, seeds 0 and 1, a shared CPU at load 4-17): the worst gate error ended
lower than the defaults' on both tables (Table 4: 0.163 and 0.056 against 0.299 and 0.265;
Table 2: 0.020 and 0.019 against 0.036 and 0.042), and on Table 2 it stayed within 2% from
566-687 s, which neither the defaults nor the plain loop reached in 60 iterations. But an
iteration cost 4.7-11x the defaults' (J by differences under prbvolpath and for eta), and on
Table 4 none of the three reached 2%. On the matrix's Table 4 cell at max_depth 8, spp 16
(128x96, 3 seeds) it ended worse on every seed (9.7-14.8% against the defaults' 4.6-9.9%) in
7 times their time: at 16 spp the differences of sigma_t, eta and alpha are noise, so H and g
are too (docs/benchmarks-history.md, 2026-11-28). A default must win or tie in every cell it
applies to, so it stays off unless named.
"""

from __future__ import annotations

import math

import numpy as np

from ...engine_api import SMALL
from .. import parameters, trust_region
from ..losses import LOSSES
from .base import HOLD, Choice

EVERY = 1              # a step every EVERY-th iteration
MAX_COMPONENTS = 12    # J costs a pass per scalar or colour at every iteration: a handful
RADIUS = 2.0           # the first step's radius, in difference steps (jacobian._latent_step)
KINDS = ("scalar", "rgb")  # textures, grids, vertices and transforms keep Adam
SEED = 104_729         # J's samples: the job's seed and the iteration, apart from the renders'


class GaussNewton(Choice):
    name = "gauss_newton"

    def select(self, ctx, records):
        keys = [k for k, r in records.items() if r.scene is not None and r.size <= SMALL
                and r.kind in KINDS]
        count = sum(records[k].size for k in keys)
        self.refused = ""
        if keys and count > MAX_COMPONENTS:
            self.refused = (f"{count} scalar and colour components, more than "
                            f"{MAX_COMPONENTS}: J's passes at every iteration would cost many "
                            "renders")
        elif keys and not LOSSES[ctx.settings.loss].least_squares:
            self.refused = f"the loss {ctx.settings.loss} is not least squares"
        return [] if self.refused else keys

    def setup(self, ctx, records, state) -> None:
        self.applies = bool(records)
        if self.refused and self.on:
            ctx.note(f"gauss_newton: does not apply ({self.refused}); Adam steps them")
        if not self.applies:
            return
        self.sizes = [records[k].size for k in self.keys]
        state = state or {}
        self.radius = float(state["radius"][0]) if "radius" in state else RADIUS
        # v of the current values, and of the pending step's start with the estimate there
        # (hessian, gradient, spread, noise) and the step (delta, its predicted fall, length)
        self.point, self.base = state.get("point"), state.get("base")
        self.fit = {k: state[k] for k in ("hessian", "gradient", "spread", "noise")
                    if k in state}
        self.delta = state.get("delta")
        self.predicted, self.length = (float(x) for x in state.get("step", (0.0, 0.0)))
        self.counts = state["counts"].astype(int) if "counts" in state else np.zeros(3, int)
        self.damped = [int(k) for k in state.get("damped", [])]
        self._say()

    def _say(self) -> None:
        kept, undone, steps = (int(n) for n in self.counts)
        self.why = (f"{', '.join(self.keys)} stepped by damped Gauss-Newton (J from two "
                    f"independent estimates) every {EVERY} iteration(s) in a trust region, "
                    "in place of Adam" if self.on else
                    f"{', '.join(self.keys)} stepped by Adam (on: by damped Gauss-Newton in a "
                    "trust region, from J's two independent estimates)")
        if self.on and steps:
            self.why += (f"; {steps} steps, {kept} kept, {undone} undone, radius "
                         f"{self.radius:.3g} difference steps")
        if self.on and self.damped:
            names = ", ".join(self._component(k) for k in self.damped)
            self.why += f"; damped (the images do not resolve it): {names}"

    def _component(self, n: int) -> str:
        for key, size in zip(self.keys, self.sizes):
            if n < size:
                return key if size == 1 else f"{key}[{n}]"
            n -= size

    def _split(self, flat: np.ndarray) -> dict[str, np.ndarray]:
        return dict(zip(self.keys, np.split(flat, np.cumsum(self.sizes)[:-1])))

    def before_render(self, ctx) -> dict[str, object]:
        # the renderer's: imported once its variant is set (the daemon reads the choices first)
        from ..jacobian import _latent_step, quantity
        i = ctx.iteration
        if i % EVERY:
            return {}
        if self.point is None:
            self.point = np.concatenate([ctx.initial[k] for k in self.keys]).astype(float)
        values = self._split(self.point)
        quantities = [quantity(k, values[k], ctx.kept(k)) for k in self.keys]
        with ctx.holding(values):
            fit = ctx.linearize(quantities, ctx.settings.seed + SEED * i).fit
        n = len(self.point)
        here = {"hessian": fit.hessian[:n, :n], "gradient": fit.gradient[:n],
                "spread": fit.spread[:n, :n],
                # the gradient's covariance: the render noise of two renders, J's own noise
                "noise": fit.noise[:n, :n] / 2 + np.diag(fit.gradient_noise[:n])}
        if self.base is not None:  # the pending step's outcome
            fell, noise = trust_region.fall(self.fit["gradient"], here["gradient"],
                                            self.fit["noise"], here["noise"], self.delta)
            kept, self.radius = trust_region.judge(fell, noise, self.predicted,
                                                   self.length, self.radius)
            self.counts[0 if kept else 1] += 1
            if not kept:  # undone: from the start again, with its estimate
                self.point, here = self.base, self.fit
                quantities = [quantity(k, v, ctx.kept(k))
                              for k, v in self._split(self.point).items()]
        u, lo, hi = (np.concatenate(x) for x in zip(*(_latent(q) for q in quantities)))
        scale = np.concatenate([np.full(q.value.size, _latent_step(q)) for q in quantities])
        proposal = trust_region.step(here["hessian"], here["gradient"], here["spread"], scale,
                                     self.radius, u, lo, hi)
        self.base, self.fit, self.delta = self.point, here, proposal.delta
        self.predicted, self.length = proposal.predicted, proposal.length
        self.point = np.concatenate([np.exp(m) if q.log else m for q, m in zip(
            quantities, np.split(u + proposal.delta, np.cumsum(self.sizes)[:-1]))])
        self.damped = proposal.damped
        self.counts[2] += 1
        self._say()
        return {k: parameters.assign(ctx.variable(k), ctx.encoded(k, v))
                for k, v in self._split(self.point).items()}

    def on_gradient(self, ctx) -> dict[str, object]:
        return dict.fromkeys(self.keys, HOLD)  # stepped here, not by Adam

    def state(self):
        if not self.applies:
            return {}
        out = {"radius": np.array([self.radius]), "counts": self.counts,
               "step": np.array([self.predicted, self.length]),
               "damped": np.array(self.damped, np.int64)}
        if self.point is not None:
            out["point"] = self.point
        if self.base is not None:
            out.update(base=self.base, delta=self.delta, **self.fit)
        return out

    def notes(self) -> list[str]:
        return [f"gauss_newton: {self.why}"] if self.on else []


def _latent(q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """u, and its bounds, in the coordinates J is taken in (log v for a log parameter)."""
    lo = max(q.lo, q.floor)
    if not q.log:
        return q.value.astype(float), np.full(q.value.size, lo), np.full(q.value.size, q.hi)
    bottom = math.log(max(lo, 1e-6))
    top = math.log(q.hi) if math.isfinite(q.hi) else 40.0
    return np.log(np.maximum(q.value, 1e-6)), np.full(q.value.size, bottom), np.full(
        q.value.size, top)
