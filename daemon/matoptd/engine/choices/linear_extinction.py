"""A homogeneous medium's extinction stepped linearly, at a rate scaled to where it stands.

log_space would step sigma_t as u = log v: a relative step, so from a start of 0.99 down to a
truth of 0.4 each step shrinks with the value (2.5 times smaller there than at the start). On
the thesis's Table 4 scene (a rough dielectric around a homogeneous medium) sigma_t so stepped
came nearest its truth at iteration 40 (7.7% off), then, with eta released, slid along the
valley it shares with eta and the interface's alpha and ended 9.3% off (3 seeds), where the
plain loop's linear steps ended 5.9% off. Stepped linearly instead, the worst of albedo,
sigma_t and eta ended at 7.8% and 6.3% against the plain loop's 9.7% and 7.3% in the same run
(docs/benchmarks-history.md).

So a homogeneous medium's scalar sigma_t is stepped as it is, with the step

    lr_i = lr * max(v_{i-1}, v_0)          (v_0: its start)

below the start an absolute step, the start's share as the plain loop takes it near there (a
thin truth decades below is reached in 1/lr steps, down to 0, its legal minimum); above it a
relative step as log space's, so an optically thick truth decades above the start is reached in
as many steps as there. The rate a user gives is read the same way, and the job's notes say so.
A grid's extinction stays in log space (its texels span decades; bench/grids.py).
"""

from __future__ import annotations

from .. import parameters
from .base import Choice


class LinearExtinction(Choice):
    name = "linear_extinction"

    def select(self, ctx, records):
        return [k for k, r in records.items()
                if r.scene is not None and parameters.homogeneous_extinction(k, r.size)]

    def setup(self, ctx, records, state) -> None:
        self.starts = {k: float(r.start[0]) for k, r in records.items()}
        self.base = {k: r.rate for k, r in records.items()}
        self.applies = bool(self.starts)
        keys = ", ".join(sorted(self.starts))
        self.why = (f"{keys} stepped linearly, by its rate times the larger of its value and its "
                    "start: log space's relative steps shrink as it falls and leave it along the "
                    "valley it shares with an interface's eta and roughness" if self.on else
                    f"{keys} stepped as log_space says")

    def rate(self, record, rate: float) -> float:
        # current holds theta_{i-1} (read with the last loss): no extra sync for the value
        start = self.starts[record.key]
        now = float(record.current[0]) if record.current is not None else start
        return rate * max(now, start, 1e-30)

    def notes(self) -> list[str]:
        return [f"{k}: stepped linearly, its rate {self.base[k]:g} a share of the larger of its "
                f"value and its start ({s:g}): {self.base[k] * s:.3g} per step at full rate "
                "below the start, that share of the value above it"
                for k, s in sorted(self.starts.items())]
