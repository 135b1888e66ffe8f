"""Adam's momentum lowered in a job that optimizes a homogeneous medium's albedo and sigma_t.

Adam's first moment is an average of the last gradients,

    m_i = beta_1 m_{i-1} + (1 - beta_1) g_i,

over about 1 / (1 - beta_1) of them: 10 at Dr.Jit's beta_1 of 0.9, 2 at BETA_1. A medium's
albedo and sigma_t share a valley (a darker albedo and a thinner medium look alike). Started far
off, the pair crosses the valley's floor with ten gradients' worth of momentum and swings along
it. On the thesis's Table 4 scene (started at albedo 0.01, sigma_t 0.99) the albedo's red
channel rose to 0.56 by iteration 20, fell to 0.16-0.22 by iteration 45 and was back at 0.45
by iteration 75, with sigma_t swinging against it, on the daemon's side and on Mitsuba's plain
loop alike: at the 100th iteration the swing had not died out, and where a job ended depended
on its phase. At BETA_1 the pair comes down to the floor with little overshoot.

The price is noisier steps: each averages fewer gradients. At medium_constant_rate's undecayed
rate the pair then jitters to the end, so it was measured with that choice off (the schedule's
decay brings the steps down). Dr.Jit's Adam has one beta_1 per optimizer, so every variable of
the job takes it (as large_steps' uniform mode); BETA_1 on the pair alone, eta and the
interface's width at 0.9, did no better. Only for a medium whose albedo and sigma_t are both
selected, neither given a rate (as medium_constant_rate). A candidate, off unless named: on
Table 4's nine cells of bench/defaults_matrix.py it ended lower than the defaults in seven and
within the seeds' spread in two. But without the swing's overshoot, and with the decay, a
short job ends with the pair still climbing: on the 32 px, 60-iteration analogue in
tests/test_thesis_tables.py the albedo ended 18% off, against 8-9% on the defaults
(docs/benchmarks.md).
"""

from __future__ import annotations

from .. import parameters
from .base import Choice

BETA_1 = 0.5


class MediumDamping(Choice):
    name = "medium_damping"

    def select(self, ctx, records):
        return parameters.medium_pairs(records)

    def setup(self, ctx, records, state) -> None:
        self.applies = bool(records)
        pair = ", ".join(sorted(records))
        if self.on:
            self.adam_beta_1 = BETA_1
            self.why = (f"Adam's beta_1 {BETA_1:g} in place of 0.9 for {pair} (Dr.Jit's is per "
                        "optimizer: every parameter of the job): with less momentum the pair "
                        "does not swing along the valley it shares")
        else:
            self.why = f"Adam's beta_1 0.9 for {pair}, as for every variable"
