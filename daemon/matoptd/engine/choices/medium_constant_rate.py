"""A homogeneous medium's albedo and extinction stepped at their full rate to the job's end.

The schedule's decay (to a tenth of each rate, optimize.schedule_factor) is there for noise:
late steps that only follow it should be small. A medium's albedo and sigma_t end otherwise:
they share a valley (a darker albedo and a thinner medium look alike), along which their
gradients are small beside their noise, and the decay stops them short of its bottom. On the
thesis's Table 4 scene at max_depth 8, spp 16, the jobs' notes said the albedo was still
moving at the end, and the last iterates averaged were no closer than the last one: they end
short of the truth, not in a ball of noise. With this choice (and slow_interface_width) the
median worst gated error over 8 seeds was 2.85% against the defaults' 8.2% in the same hour
and the plain loop's 3.0% at equal time (docs/benchmarks-history.md, 2026-11-29 evening).

Off unless named, until the matrix of depths and spp decides (bench/defaults_matrix.py).
Grids keep the decay: their texels are many and each is seen by few pixels.
"""

from __future__ import annotations

from .. import parameters
from .base import Choice


class MediumConstantRate(Choice):
    name = "medium_constant_rate"
    writes = ("decays",)

    def select(self, ctx, records):
        return [k for k, r in records.items() if r.scene is not None
                and parameters.homogeneous_medium_property(k, r.kind)]

    def setup(self, ctx, records, state) -> None:
        self.applies = bool(records)
        keys = ", ".join(sorted(records))
        self.why = (f"{keys} stepped at their full rate to the end (no decay): the decay stops "
                    "a medium's albedo and extinction short along the valley they share"
                    if self.on else f"{keys} decay with the schedule, as every variable does")
        if self.on:
            for r in records.values():
                r.decays = False
