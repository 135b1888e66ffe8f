"""A dielectric's eta held at its start while the other parameters still move steadily.

Far from the truth, the images ask eta for what the medium and the lobes cannot give yet: on
the thesis's Table 4 scene (a rough dielectric around a homogeneous medium, started at albedo
0.01, sigma_t 0.99, alpha 0.98) eta ran from 1.55 to 1.70 in the first 20 iterations while
albedo and sigma_t were still far off, and never came back (final eta 3-11% off). Eta is
therefore held (its gradient zeroed: Adam, with ``mask_updates``, then leaves it and its
moments alone) until every other parameter has settled: over the last WINDOW iterations its
net move, in the space it is stepped in, is less than SETTLED of the full steps its rate
allowed (a steady descent moves by about its rate each step; a parameter that jitters about
its optimum nets a small fraction of that). It is never held past HOLD_SHARE of the job.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from ...engine_api import SMALL
from .. import parameters
from .base import Choice

WINDOW = 10
SETTLED = 0.5
HOLD_SHARE = 0.5


class EtaHold(Choice):
    name = "eta_hold"

    def setup(self, loop, state) -> None:
        self.etas = [k for k in loop.parameters if parameters.dielectric_eta(k)]
        self.others = [k for k in loop.parameters
                       if k not in self.etas and loop.starts[k].size <= SMALL]
        self.applies = bool(self.etas and self.others)
        saved = state.get("released") if state else None
        self.released = int(saved[0]) if saved is not None else -1  # the iteration; -1: held
        self.path: list[dict[str, np.ndarray]] = []  # the others' variables, latest last
        self.rates: list[dict[str, float]] = []     # their rates at each of those steps
        self.last = max(1, round(HOLD_SHARE * loop.settings.iterations))
        self.why = (f"{', '.join(self.etas)} held at its start until "
                    f"{', '.join(self.others)} settle (each nets less than {SETTLED:g} of its "
                    f"full steps over {WINDOW} iterations; at most until iteration {self.last}): "
                    "far off, the images push eta to stand in for them, and it did not come "
                    "back" if self.on else f"{', '.join(self.etas)} stepped from the start")
        if self.released >= 0:
            self.why += f"; released at iteration {self.released}"

    def settled(self) -> bool:
        if len(self.path) <= WINDOW:
            return False
        first, last = self.path[-WINDOW - 1], self.path[-1]
        for key in self.others:
            allowed = sum(r[key] for r in self.rates[-WINDOW:])
            if np.max(np.abs(last[key] - first[key])) > SETTLED * allowed:
                return False
        return True

    def on_gradient(self, loop, i: int, sensors) -> None:
        if self.released >= 0:
            return
        self.path = (self.path + [{k: loop.variable(k) for k in self.others}])[-WINDOW - 1:]
        self.rates = (self.rates + [{k: loop.rate(k) for k in self.others}])[-WINDOW:]
        if self.settled() or i >= self.last:
            self.released = i
            self.why += (f"; released at iteration {i} ("
                         + ("the others settled)" if i < self.last else "the hold's limit)"))
            return
        for key in self.etas:
            dr.set_grad(loop.opt[key], 0.0)
            loop.frozen.add(key)

    def state(self):
        return {"released": np.array([self.released], np.int64)}
