"""The microfacet width beside a dielectric's eta differentiated by central differences of the
images in its step space, in place of the AD gradient, while the surface is narrow.

Near the specular limit a back-propagated gradient of the width carries almost nothing: on the
thesis's Table 4 scene at its truth (alpha 0.01) its variance is 3,700-7,300 times what the
images leave (bench/information.py). A job's width stops where its noise outweighs its slope
(alpha 0.05-0.11 for a truth of 0.01), and a denser medium makes up for the wider lobe. While
the width shows alpha below WIDE, with u its step variable (u = log v under log_space):

    h D = (I(v(u + h)) - I(v(u - h))) / 2     (both sides from the same samples)
    dL/du ~ (L(I + h D) - L(I - h D)) / 2h    (I: this iteration's own renders)

as eta's differences (eta_differences.py). Its cost: two primal renders at a quarter of the
job's spp per width and sensor, while it applies.

A candidate, off unless named (``--choice width_differences=on``): the matrix
(bench/defaults_matrix.py) decides whether it becomes a default.
"""

from __future__ import annotations

import math

import numpy as np

from .. import parameters
from .base import Choice
from .eta_differences import loss_slope, side_difference

WIDE = 0.2        # alpha below which the differences apply: prb's own gradient above
STEP = 0.1        # h in u: under log_space the sides are 10% either side of v
DIVISOR = 4       # the sides at a quarter of the job's spp


class WidthDifferences(Choice):
    name = "width_differences"
    yields_to = ("gauss_newton",)  # which steps the widths it selects, while on
    wants_images = True
    after = ("log_space", "exposure_gains")  # u's map; the gained renders

    def select(self, ctx, records):
        etas = [k for k, r in records.items()
                if r.scene is not None and parameters.dielectric_eta(k)]
        widths = {w for e in etas for w in parameters.microfacet_widths(e, records)}
        return [w for w in sorted(widths) if records[w].kind == "scalar"]

    def setup(self, ctx, records, state) -> None:
        self.ranges = {k: (r.lo, r.hi) for k, r in records.items()}
        self.applies = bool(records)
        keys = ", ".join(sorted(records))
        self.why = (f"{keys} by central differences of the loss in its step variable while it "
                    f"shows alpha < {WIDE:g} (its sides at 1/{DIVISOR} of the job's spp): near "
                    "the specular limit its back-propagated gradient is mostly noise" if self.on
                    else f"{keys}: the gradient from back-propagation alone, at any width")

    def on_gradient(self, ctx) -> dict[str, object]:
        out = {}
        spp = max(1, ctx.spp // DIVISOR)
        for key in self.keys:
            v = ctx.value(key)
            if key in ctx.held or parameters.microfacet_alpha(key, v) >= WIDE:
                continue  # the AD gradient stands
            u, logged = float(ctx.latent(key)[0]), ctx.kept(key).log
            lo_, hi_ = self.ranges[key]
            # the sides in v, inside the range; their distance in u scales D to one of h
            down, up = (math.exp(x) if logged else x for x in (u - STEP, u + STEP))
            lo, hi = max(down, lo_), min(up, hi_)
            du = float(ctx.encoded(key, np.array([hi]))[0] - ctx.encoded(key, np.array([lo]))[0])
            if not (hi > lo and du > 0):
                continue
            out[key] = loss_slope(ctx, side_difference(ctx, key, lo, hi, STEP / du, spp), STEP)
        return out

    def notes(self) -> list[str]:
        return [f"{k}: its gradient by central differences of the loss while it shows alpha < "
                f"{WIDE:g} (u +- {STEP:g} in its step variable, the same samples on both "
                "sides): there its back-propagated gradient is mostly noise" for k in self.keys]

