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

    def setup(self, loop, state) -> None:
        self.keys = sorted(k for k, start in loop.starts.items()
                           if parameters.black_tint(k, start))
        self.applies = bool(self.keys)
        self.why = (f"{', '.join(self.keys)} started at {parameters.NEUTRAL_START:g} instead of "
                    "black: a black colour makes the lobes it tints black, and what they carry "
                    "gets no gradient" if self.on else
                    f"{', '.join(self.keys)} started black, as given")
        if self.on:
            for key in self.keys:
                p = loop.parameters[key]
                loop.starts[key] = np.full_like(
                    loop.starts[key], np.clip(parameters.NEUTRAL_START, p.lo, p.hi))

    def notes(self) -> list[str]:
        return [f"{k}: started at {parameters.NEUTRAL_START:g} instead of black: a black "
                "colour makes the lobes it tints black, and what they carry gets no gradient"
                for k in self.keys]
