"""A dielectric's eta differentiated by central differences of the images near the specular
limit, in place of the AD gradient.

prb and prbvolpath sample the refracted direction detached from eta, so their gradient of eta
holds only the Fresnel weights, not where the refracted rays go, which decides the image once
the lobe is narrow: on glass at the roughness floor its sign was random at every eta from 1.40
to 1.70; at alpha 0.01 wrong 2 times in 5; from alpha 0.029 up it matched the difference. While
every width beside an eta shows alpha below settings.SPECULAR_ALPHA, or the value's ALPHA (read
at each iteration, so an optimized roughness that sharpens switches it on; a smooth dielectric
always):

    D = (I(eta + h) - I(eta - h)) / 2h           (both sides from the same samples)
    dL/d(eta) ~ (L(I + h D) - L(I - h D)) / 2h   (I: this iteration's own renders)

The difference of the losses themselves would also follow the render noise's variance, which
changes with eta (on a rough principled object it ended at eta 1.45 for a truth of 1.49); I is
independent of D's samples, as Mitsuba's adjoint pass is of its primal pass. Its cost: two
primal renders at a quarter of the job's spp per eta and sensor (the choice's value ``full``:
at the job's spp), only while it is on. Where the iterations are frozen, I comes out of the
iteration's recording and the two renders replay one of their own (engine/frozen.py), eta +- h
set outside it on the scene it reads.

Most of the slope's noise is D's, not I's: refracted paths part between eta - h and eta + h,
so the shared samples cancel less than they would for a reflectance. On the thesis's Table 2
scene at its truth (max_depth 8) D at 2 spp a side carries some 150 times as much noise as
signal, summed over the pixels (two estimates of D at 256 spp, bench/information.py). Once
eta has settled (settling.py: over the last WINDOW iterations it netted less than SETTLED of
the steps its rate allowed), J hardly moves, so D is the mean of the last KEPT differences, a
new one taken every EVERY-th iteration, and eta is stepped at every iteration on that mean and
the iteration's own I. While eta moves, D moves with it and the newest difference stands
alone. On Table 2 at max_depth 8, spp 8 (16 seeds, docs/benchmarks-history.md) the worst gated
error's median went from 2.1% (a single D, eta stepped only with a new one) to 0.9%, better
on 12 seeds.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ...settings import differences
from .. import parameters
from .base import Choice
from .settling import restored_paths

# By default the sides take a quarter of the job's spp (settings.DIFFERENCE_SPP): both share
# their samples, so most noise cancels. On the Table 2 and 3 kinds eta ended as close as at full
# spp (0.0-0.5%) and an iteration took 25% less time.
STEP = 0.01   # h: 1% of the range near 1.5
DRAW = 0x9E3779B9  # samples of their own, shared by both sides
EVERY = 4     # once eta has settled, its difference every EVERY-th iteration
KEPT = 16     # once settled, D is the mean of the last KEPT differences


class EtaDifferences(Choice):
    name = "eta_differences"
    yields_to = ("gauss_newton",)  # which steps eta by Gauss-Newton, while on
    wants_images = True
    after = ("exposure_gains", "eta_hold")  # the gained renders; no differences while held

    def select(self, ctx, records):
        """Each eta, and the optimized widths beside it (read at every iteration)."""
        etas = [k for k, r in records.items()
                if r.scene is not None and parameters.dielectric_eta(k)]
        return etas + [w for k in etas for w in parameters.microfacet_widths(k, records)]

    def setup(self, ctx, records, state) -> None:
        # Per eta, the widths beside it and the values of those not optimized. Read from a
        # traversal of their own: a key read through ctx.params is marked for its update(),
        # which then fails on the keys that keep() dropped.
        widths = mi.traverse(ctx.scene)
        self.widths = {k: {w: parameters.flat(widths[w])
                           for w in parameters.microfacet_widths(k, widths.keys())}
                       for k in records if parameters.dielectric_eta(k)}
        del widths
        self.optimized = [k for k in records if k not in self.widths]
        self.ranges = {k: (r.lo, r.hi) for k, r in records.items()}
        self.paths = restored_paths(state, self.widths)
        saved = state.get("sparse") if state else None
        self.sparse = int(saved[0]) if saved is not None else 0  # on the kept D alone
        # Per eta and sensor, h D's mean (a list: the sensor's renders) and the differences
        # in it: D's noise, not the images', is most of the slope's.
        self.kept: dict[str, dict[int, list]] = {k: {} for k in self.widths}
        self.taken: dict[str, dict[int, int]] = {k: {} for k in self.widths}
        for n, k in enumerate(self.widths):
            for s, count, taken in (state or {}).get(f"kept{n}", np.zeros((0, 3))):
                s = int(s)
                self.taken[k][s] = int(taken)
                self.kept[k][s] = [mi.TensorXf(state[f"kept{n}_{s}_{j}"])
                                   for j in range(int(count))]
        self.applies = bool(self.widths)
        self.integrator = ctx.chosen.name
        self.how = differences(self.settings.choice_value(self.name) if self.on else "on")
        share = ("the job's spp" if self.how.divisor == 1
                 else f"1/{self.how.divisor} of the job's spp")
        self.said = ("; ".join(f"{k} by central differences of the loss {self._when(k)}"
                               for k in self.widths)
                     + f" (once it settles a new difference every {EVERY}th iteration, eta "
                     f"stepped at every one on the mean of the last {KEPT}; its sides at "
                     f"{share}): "
                     f"{self.integrator} samples the refracted direction detached from eta, so "
                     "near the specular limit its own gradient of eta misses where the "
                     "refracted rays go" if self.on else
                     f"{', '.join(self.widths)}: the gradient from back-propagation alone, at "
                     "any width")
        self._say()

    def _say(self) -> None:
        self.why = self.said + (f"; {self.sparse} iterations on the kept mean without a new "
                                "difference so far" if self.sparse else "")

    def _when(self, key: str) -> str:
        w = self.widths[key]
        return (f"while {' and '.join(w)} shows alpha < {self.how.alpha:g}" if w
                else "(a smooth dielectric)")

    def on_gradient(self, ctx) -> dict[str, object]:
        i, out = ctx.iteration, {}
        theta = {k: ctx.value(k) for k in [*self.widths, *self.optimized]}
        spp = max(1, ctx.spp // self.how.divisor)
        for key, widths in self.widths.items():
            path = self.paths[key]
            if key in ctx.held or not parameters.near_specular(widths, theta, self.how.alpha):
                path.add(ctx.latent(key), 0.0 if key in ctx.held else ctx.rate(key))
                continue  # held, or the AD gradient stands
            path.add(ctx.latent(key), ctx.rate(key))
            lo_, hi_ = self.ranges[key]
            v = float(theta[key][0])
            lo, hi = max(v - STEP, lo_), min(v + STEP, hi_)
            if not hi > lo:
                continue
            settled = path.settled()
            if not (settled and i % EVERY) or any(s not in self.kept[key]
                                                  for _, s in ctx.sensors):
                self._difference(ctx, key, lo, hi, spp, settled)
            else:
                self.sparse += 1
                self._say()
            # left to Dr.Jit: the step evaluates it, with no read back of its own per iteration
            slope = mi.Float(0.0)
            with dr.suspend_grad():
                for _, sensor in ctx.sensors:
                    d = self.kept[key][sensor]
                    images = ctx.images[sensor]
                    up = ctx.image_loss([x + y for x, y in zip(images, d)], sensor)
                    down = ctx.image_loss([x - y for x, y in zip(images, d)], sensor)
                    slope += dr.ravel(up - down)
            out[key] = slope / (2 * STEP * len(ctx.sensors))
        return out

    def _difference(self, ctx, key: str, lo: float, hi: float, spp: int, settled: bool
                    ) -> None:
        """A new h D from renders at eta's two sides: once eta has settled, into the mean of
        the last KEPT; while it moves, D moves with it and the newest stands alone."""
        sides = []
        for side in (lo, hi):
            with ctx.holding({key: np.array([side])}), dr.suspend_grad():
                sides.append({sensor: ctx.sensor_images(n, sensor, DRAW, spp)
                              for n, sensor in ctx.sensors})
        kept, taken = self.kept[key], self.taken[key]
        with dr.suspend_grad():
            for _, sensor in ctx.sensors:
                d = [(b - a) * (STEP / (hi - lo))
                     for a, b in zip(sides[0][sensor], sides[1][sensor])]
                taken[sensor] = taken.get(sensor, 0) + 1 if settled else 1
                w = 1.0 / min(taken[sensor], KEPT)
                old = kept.get(sensor) if taken[sensor] > 1 else None
                kept[sensor] = d if old is None else [m + (x - m) * w for m, x in zip(old, d)]
                dr.eval(kept[sensor])

    def state(self):
        out = {"sparse": np.array([self.sparse], np.int64)}
        for n, (key, path) in enumerate(self.paths.items()):
            out.update(path.state(f"path{n}"))
            if self.kept[key]:
                out[f"kept{n}"] = np.array([(s, len(d), self.taken[key][s])
                                            for s, d in self.kept[key].items()], np.int64)
                out.update({f"kept{n}_{s}_{j}": np.array(x, np.float32)
                            for s, d in self.kept[key].items() for j, x in enumerate(d)})
        return out

    def notes(self) -> list[str]:
        return [f"{k}: its gradient by central differences of the loss {self._when(k)} (eta +- "
                f"{STEP:g}, the same samples on both sides): {self.integrator} samples the "
                "refracted direction detached from eta, so near the specular limit its own "
                "gradient of eta misses where the refracted rays go" for k in self.widths]
