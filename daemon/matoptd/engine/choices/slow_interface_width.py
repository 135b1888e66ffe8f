"""The microfacet width of a dielectric around a medium stepped at half the width rate.

Near the specular limit a back-propagated gradient of eta carries almost nothing: on the
thesis's Table 4 scene at alpha 0.01 its variance is 2,000-5,000 times what the images leave
(bench/information.py). Its information comes while the interface is still rough. At the
width rate (0.2, a 20% change per step) alpha falls from its start 0.98 to 0.02 within 25
iterations, while eta is still held behind a medium far off (eta_hold); by its release eta has
no gradient left to go by, and the medium makes up for its error. At half that rate (0.1) the
interface stays rough while eta moves: on Table 4 at max_depth 8, spp 16 (8 seeds) eta ended
a median 1.0% off against the defaults' 2.8% (docs/benchmarks-history.md, 2026-11-29 evening).

Only for a width the job gave no rate for, beside a dielectric's eta with a medium selected:
without a medium, eta_differences decides eta near the specular limit (Table 2), and a width
crossing decades (0.5 to 0.001) needs the full rate to get there in a short job.

Off unless named (``--choice slow_interface_width=on``). At the scene file's own depth (64, cut
to 32), spp 16, the half rate leaves alpha stopped at 0.05-0.064 and a denser medium making up
for the wider lobe: over 8 seeds a median worst gated error of 7.1% with it against 3.4%
without (better on 7 of 8). At max_depth 8, spp 32 without it: 1.2% against 2.0% over 5 seeds,
two of them at 7%: a tie within the seeds' spread. At the own depth, spp 32 it was ahead on 3
of 4 seeds, in a cell lost either way (docs/benchmarks-history.md, 2026-11-30).
"""

from __future__ import annotations

from .. import parameters
from .base import Choice

SHARE = 0.5  # of the listed width rate


class SlowInterfaceWidth(Choice):
    name = "slow_interface_width"
    after = ("log_space",)  # a share of the relative rate log space steps the width by

    def select(self, ctx, records):
        keys = [k for k, r in records.items() if r.scene is not None]
        if not any(parameters.homogeneous_medium_property(k, records[k].kind) for k in keys):
            return []
        etas = [k for k in keys if parameters.dielectric_eta(k)]
        return [w for eta in etas for w in parameters.microfacet_widths(eta, keys)
                if not records[w].rate_given and records[w].kind == "scalar"]

    def setup(self, ctx, records, state) -> None:
        self.applies = bool(records)
        self.rates = {k: r.rate for k, r in records.items()}
        keys = ", ".join(sorted(records))
        self.why = (f"{keys} stepped at {SHARE:g} of its listed rate: eta beside it has a "
                    "gradient to go by only while the interface is rough" if self.on else
                    f"{keys} stepped at its listed rate (on: at {SHARE:g} of it, so that eta "
                    "beside it moves while the interface is rough)")

    def rate(self, record, rate: float) -> float:
        return rate * SHARE

    def notes(self) -> list[str]:
        return [f"{k}: stepped at {SHARE:g} of its listed rate, {SHARE * r:g} in place of {r:g} "
                "(slow_interface_width), so that eta beside it moves while the interface is "
                "rough" for k, r in sorted(self.rates.items())]
