"""A principled roughness rendered at no less than the floor its BSDF can show.

The principled BSDF uses alpha = max(0.001, roughness^2): below ~0.0316 its specular lobe
stops changing and its gradient is exactly 0. The roughness is rendered and reported at no
less than parameters.ROUGHNESS_FLOOR (0.0318^2 = 0.00101, within 1.2% of the floor in alpha)
while the value Adam steps on may go on down to the range's minimum, steered there by the
floor's gradient:

    v_shown = v + detach(max(v, floor) - v)      (d v_shown / d v = 1)

A hard bound at the floor would reflect: a step down clipped, one up not, so on the level loss
of a near-specular truth noise walks it away; below the floor the walk is free. The price: a
truth just above the floor that the images hardly show can end there too
(docs/benchmarks.md, Table 2).
"""

from __future__ import annotations

import dataclasses

import drjit as dr

from .. import parameters
from .base import Choice


class RoughnessFloor(Choice):
    name = "roughness_floor"

    after = ("log_space",)  # the floor is v's: after u = log v is decoded

    def select(self, ctx, records):
        return [k for k, r in records.items()
                if r.scene is not None and parameters.shown_floor(k, r.lo) > 0]

    def setup(self, ctx, records, state) -> None:
        self.floors = {k: parameters.shown_floor(k, r.lo) for k, r in records.items()}
        self.applies = bool(self.floors)
        keys = ", ".join(sorted(self.floors))
        self.why = (f"{keys} rendered and reported at no less than {parameters.ROUGHNESS_FLOOR:g}"
                    " (alpha 0.001, the least the principled BSDF shows) while Adam steps on "
                    "below it on the floor's gradient: a hard bound there would reflect noise"
                    if self.on else f"{keys} rendered as stepped: below "
                    f"{parameters.ROUGHNESS_FLOOR:g} the lobe no longer changes and the gradient "
                    "is 0")

    def decode(self, key: str, latent):
        floor = self.floors[key]
        return latent + dr.detach(dr.maximum(latent, floor) - latent)

    def kept(self, key: str, kept):
        return dataclasses.replace(kept, floor=self.floors[key])
