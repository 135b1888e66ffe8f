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

The price is noisier steps: each averages fewer gradients. At an undecayed rate
(medium_constant_rate's) the pair then jitters to the end, so the choice takes the pair's
rate from that choice and says how it decays:

- ``on``: on the schedule from the job's start. The pair comes down slowly and the decay
  stops it early: on the 32 px, 60-iteration analogue of Table 4 in
  tests/test_thesis_tables.py the albedo ended 18% off (the defaults 8-9%).
- ``settle``: at its full rate until both only jitter (settling.py, by the window's spread:
  at a swing's far end a variable nets little but spans much), then on the schedule from
  that iteration. The short job passes (10% off): with less time left to decay, the pair's
  last steps are larger.

Dr.Jit's Adam has one beta_1 per optimizer, so every variable of the job takes it (as
large_steps' uniform mode); BETA_1 on the pair alone, eta and the interface's width at 0.9,
did no better. Only for a medium whose albedo and sigma_t are both selected, neither given a
rate (as medium_constant_rate). A candidate, off unless named: on Table 4's cells of
bench/defaults_matrix.py ``on`` lost two cells the defaults won; ``settle`` ended lower in
eight of nine and level in one, over 4 seeds in seven cells where the defaults' rows have 8
(docs/benchmarks.md).
"""

from __future__ import annotations

import numpy as np

from ...settings import CHOICE_OPTIONS
from .. import parameters
from .base import Choice
from .settling import SETTLED, WINDOW, paths_state, restored_paths

BETA_1 = 0.5


class MediumDamping(Choice):
    name = "medium_damping"
    writes = ("decays", "schedule_begin")

    def select(self, ctx, records):
        return parameters.medium_pairs(records)

    def setup(self, ctx, records, state) -> None:
        self.applies = bool(records)
        pair = ", ".join(sorted(records))
        if not self.on:
            self.why = f"Adam's beta_1 0.9 for {pair}, as for every variable"
            return
        self.adam_beta_1 = BETA_1
        self.settle = CHOICE_OPTIONS[self.name](self.settings.choice_value(self.name))
        saved = state.get("decaying") if state else None
        # The iteration the pair's decay began from; -1: it still climbs at its full rate
        self.decaying = int(saved[0]) if saved is not None else (-1 if self.settle else 0)
        self.records = list(records.values())
        self.paths = restored_paths(state, sorted(records))
        self._decay()
        self.why = (f"Adam's beta_1 {BETA_1:g} in place of 0.9 for {pair} (Dr.Jit's is per "
                    "optimizer: every parameter of the job): with less momentum the pair "
                    "does not swing along the valley it shares; "
                    + (f"the pair at its full rate until it settles (each spans less than "
                       f"{SETTLED:g} of its full steps over {WINDOW} iterations), then on the "
                       "schedule from there" if self.settle else "the pair on the schedule"))
        if self.settle and self.decaying >= 0:
            self.why += f"; settled at iteration {self.decaying}"

    def on_gradient(self, ctx) -> dict[str, object]:
        if not self.on or self.decaying >= 0:
            return {}
        for key, path in self.paths.items():
            path.add(ctx.latent(key), ctx.rate(key))
        if all(p.settled(spread=True) for p in self.paths.values()):
            self.decaying = ctx.iteration
            self._decay()
            self.why += f"; settled at iteration {self.decaying}"
        return {}

    def _decay(self) -> None:
        # While the pair climbs it keeps its whole rate; once on the valley's floor the
        # schedule's decay, run from there, averages its noise.
        for r in self.records:
            r.decays = self.decaying >= 0
            r.schedule_begin = max(self.decaying, 0)

    def state(self):
        if not self.on:
            return {}
        return {"decaying": np.array([self.decaying], np.int64), **paths_state(self.paths)}
