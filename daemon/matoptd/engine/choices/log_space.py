"""Positive unbounded values and microfacet widths stepped in log space.

A parameter positive and unbounded above (radiance, extinction, a scale) is stepped as
u = log v: Adam's step of about lr changes v by a factor of about e^lr, the same relative
change at 1e-3 as at 1e3, so a radiance near 1000 and a reflectance near 0.5 share one
learning rate, and v never steps below 0. A microfacet width (a principled roughness, an
alpha) is too, clipped in log space to its range: a near-specular truth (alpha 0.001-0.01)
lies decades below a rough start, where a linear step of 0.1 is ten times the value and noise
kicks it between the floor and 0.3. A rate given for such a parameter is therefore a relative
step, and the job's notes say so.
"""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import numpy as np

from .. import parameters
from .base import Choice

LOG_FLOOR = 1e-6     # log(0) is -inf: a start at 0 starts at this instead
LATENT_LIMIT = 40.0  # |u| bound: e^40 ~ 2e17, far past any scene


class LogSpace(Choice):
    name = "log_space"
    yields_to = ("linear_extinction",)  # which steps a homogeneous sigma_t apart, while on

    def select(self, ctx, records):
        return [k for k, r in records.items()
                if r.scene is not None and parameters.log_space(k, r.lo, r.hi)]

    def setup(self, ctx, records, state) -> None:
        self.rates = {k: r.rate for k, r in records.items()}
        self.ranges = {k: (r.lo, r.hi) for k, r in records.items()}
        self.applies = bool(self.keys)
        self.why = (f"{', '.join(sorted(self.keys))} stepped as u = log v: a step is the same "
                    "relative change at any scale and never crosses 0, so their rates are "
                    "relative steps" if self.on else
                    f"{', '.join(sorted(self.keys))} stepped as they are (absolute steps of "
                    "their rates, clipped to their ranges)")

    def encode(self, key: str, value: np.ndarray) -> np.ndarray:
        return np.clip(np.log(np.maximum(value, LOG_FLOOR)), *self.bounds(key, 0.0, 0.0))

    def decode(self, key: str, latent):
        return dr.exp(latent)

    def bounds(self, key: str, lo: float, hi: float) -> tuple[float, float]:
        """[min, max] of u = log v: the width floor where a width's range starts at 0."""
        v_lo, v_hi = parameters.log_bounds(key, *self.ranges[key])
        return (math.log(v_lo) if v_lo > 0 else -LATENT_LIMIT,
                math.log(v_hi) if math.isfinite(v_hi) else LATENT_LIMIT)

    def kept(self, key: str, kept):
        lo, hi = parameters.log_bounds(key, *self.ranges[key])
        return dataclasses.replace(kept, lo=lo, hi=hi, log=True)

    def notes(self) -> list[str]:
        return [f"{k}: stepped in log space, so its listed rate {r:g} is a relative step (about "
                f"{100 * (math.exp(r) - 1):.3g}% of the value per step at full rate), not an "
                "absolute one" for k, r in sorted(self.rates.items())]
