"""A colour that tints other lobes, given a black start, starts at 0.5 instead.

Black makes every lobe it tints black (base_color, reflectance, albedo, ...), and what those
lobes carry (spec_trans, eta, a medium's density) then gets no gradient: on the thesis's
Table 3 kind spec_trans fell from 0.1 to 0 in five iterations from a black texture and stayed
there; from mid-grey it reached the truth, 1.0, by iteration 15.
"""

from __future__ import annotations

import numpy as np

from .. import parameters
from .base import Choice


class BlackStart(Choice):
    name = "black_start"
    writes = ("start",)

    def select(self, ctx, records):
        return sorted(k for k, r in records.items()
                      if r.scene is not None and parameters.black_tint(k, r.start))

    def setup(self, ctx, records, state) -> None:
        self.applies = bool(self.keys)
        self.why = (f"{', '.join(self.keys)} started at {parameters.NEUTRAL_START:g} instead of "
                    "black: a black colour makes the lobes it tints black, and what they carry "
                    "gets no gradient" if self.on else
                    f"{', '.join(self.keys)} started black, as given")
        if self.on:
            for r in records.values():
                r.start = np.full_like(r.start, np.clip(parameters.NEUTRAL_START, r.lo, r.hi))

    def notes(self) -> list[str]:
        return [f"{k}: started at {parameters.NEUTRAL_START:g} instead of black: a black "
                "colour makes the lobes it tints black, and what they carry gets no gradient"
                for k in self.keys]
