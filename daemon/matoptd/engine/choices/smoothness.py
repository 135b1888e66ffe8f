"""A smoothness term for textures and grids given a weight (ParameterSetting.smoothness).

The step descends L + w * mean((v_a - v_b)^2) over neighbouring texels or voxels a, b of the
variable at its current level: it damps the texel-to-texel noise of entries few pixels see,
while the images decide the pattern's low frequencies. It steers the gradient only; the loss
recorded is the image's.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .. import multires
from .base import Choice


class Smoothness(Choice):
    name = "smoothness"
    switchable = False

    def select(self, ctx, records):
        return [k for k, r in records.items() if r.smoothness > 0]

    def setup(self, ctx, records, state) -> None:
        self.weights = {k: r.smoothness for k, r in records.items()}
        self.applies = bool(self.weights)
        self.why = "asked for: " + ", ".join(f"{k} weight {w:g}"
                                             for k, w in sorted(self.weights.items()))
        self._pairs: dict[tuple[str, tuple[int, ...]], tuple[mi.UInt32, mi.UInt32]] = {}

    def on_loss(self, ctx):
        term = 0.0
        for key, weight in self.weights.items():
            u = ctx.variable(key)
            shape = tuple(int(n) for n in u.shape)
            if (key, shape) not in self._pairs:
                a, b = multires.neighbours(shape)
                self._pairs[key, shape] = (mi.UInt32(a), mi.UInt32(b))
            a, b = self._pairs[key, shape]
            v = ctx.decoded(key, u.array)
            diff = dr.gather(mi.Float, v, a) - dr.gather(mi.Float, v, b)
            term += weight * dr.mean(dr.square(diff), axis=None)
        return term
