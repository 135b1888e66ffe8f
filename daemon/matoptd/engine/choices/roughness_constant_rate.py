"""A principled roughness beside a selected eta stepped at its full rate to the job's end.

The schedule's decay (to a tenth of each rate, optimize.schedule_factor) stops a principled
roughness short on the thesis's Table 2 scene: near the specular limit its gradient is small
beside its noise, and where it stops (0.05-0.08 against a truth at the floor, 0.0316) eta and
base_color make up for the wider lobe, a percent or two off. Kept whole, it reaches the floor
sooner. Measured beside the defaults in one run each (benchmarks-history.md, 2026-11-30): at
the scene file's own depth rendered unbounded (max_depth -1 set, so not cut), spp 8, a median
worst gated error of 0.85% against 1.97% over 12 seeds, though one seed ended at 10.7% (3.0%
when run again); at max_depth 64, spp 16, 0.47%
against 0.87% (4 seeds); at max_depth 8, spp 8 and 16 and the own depth, spp 16, ties
(0.4-1.1% on both sides). A rough dielectric's alpha on Table 4 did worse kept whole (4.3%
against 2.3%), so this is the principled BSDF's roughness only.

Off unless named: ``--choice roughness_constant_rate=on``. At max_depth 64, spp 8 it did
worse (a median of 2.04% against 0.90% over 11 seeds, eta more than 2% off on 6): kept whole,
the roughness wanders (0.05-0.16 to the end) and eta with it.
"""

from __future__ import annotations

from .. import parameters
from .constant_rate import ConstantRate


class RoughnessConstantRate(ConstantRate):
    name = "roughness_constant_rate"
    why_on = ("stepped at its full rate to the end (no decay): the decay stops a principled "
              "roughness short of the specular limit, where eta and the base colour make up "
              "for the wider lobe")
    why_off = ("decays with the schedule, as every variable does (on: at its full rate to "
               "the end)")

    def select(self, ctx, records):
        # The width beside an eta the job also steps, and given no rate: a rate the job gave
        # is the job's.
        etas = [k for k, r in records.items()
                if r.scene is not None and parameters.dielectric_eta(k)]
        widths = {w for e in etas for w in parameters.microfacet_widths(e, records)}
        return [k for k in sorted(widths) if parameters.property_name(k) == "roughness"
                and not records[k].rate_given]
