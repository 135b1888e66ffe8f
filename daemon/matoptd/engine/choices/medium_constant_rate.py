"""A homogeneous medium's albedo and extinction stepped at their full rate to the job's end.

The schedule's decay (to a tenth of each rate, optimize.schedule_factor) is there for noise:
late steps that only follow it should be small. A medium's albedo and sigma_t end otherwise:
they share a valley (a darker albedo and a thinner medium look alike), along which their
gradients are small beside their noise, and the decay stops them short of its bottom. On the
thesis's Table 4 scene at max_depth 8, spp 16, the jobs' notes said the albedo was still
moving at the end, and the last iterates averaged were no closer than the last one: they end
short of the truth, not in a ball of noise. With this choice and slow_interface_width, Table 4
at max_depth 8, spp 32 ended at a median worst gated error of 1.7% over 8 seeds, against 7.6%
without them and the plain loop's 3.3% at equal time; with this choice alone (the width at its
full rate), 1.2% over 5 seeds.

Only for a medium whose albedo and sigma_t are both selected, neither given a rate: the
valley is the pair's, and a rate the job gave is the job's. Grids keep the decay: their texels
are many and each is seen by few pixels. medium_damping, while on, takes the pair and says
how its rate decays (at Adam's lower momentum the whole rate leaves it jittering). The cells
of bench/defaults_matrix.py it concerns (Table 4's) are in docs/benchmarks.md.
"""

from __future__ import annotations

from .. import parameters
from .constant_rate import ConstantRate


class MediumConstantRate(ConstantRate):
    name = "medium_constant_rate"
    yields_to = ("medium_damping",)  # which sets how the pair decays, while on
    why_on = ("stepped at their full rate to the end (no decay): the decay stops a medium's "
              "albedo and extinction short along the valley they share")
    why_off = "decay with the schedule, as every variable does"

    def select(self, ctx, records):
        # The valley is the pair's: a medium with only one of them selected, or a rate the
        # job gave, keeps the schedule.
        return parameters.medium_pairs(records)
