"""What medium_constant_rate and roughness_constant_rate share: their variables step at their
full rate to the job's end, where the schedule's decay (optimize.schedule_factor) would stop
them short of a valley's bottom. Each says which variables, and why the decay costs there.

Kept whole, they also wander along that valley once they reach it: its floor is flat, so the
noise of the gradients walks them to and fro. With the value ``settle`` the group keeps its
full rate only while it moves steadily: after every WINDOW steps in which each of its
variables netted less than SETTLED of the steps its rate allowed (settling.py), its share of
the rate is multiplied by SHRINK, down to the schedule's own floor. A steady descent keeps
the whole rate; a jitter about the bottom is averaged by ever smaller steps.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from ...settings import CHOICE_OPTIONS
from .base import Choice
from .settling import WINDOW, paths_state, restored_paths

SHRINK = 0.5   # the share after a window in which the whole group settled
FLOOR = 0.1    # the schedule's own floor (optimize.schedule_factor)


class ConstantRate(Choice):
    writes = ("decays",)
    why_on: ClassVar[str]   # after the keys, when on: what the decay would cost
    why_off: ClassVar[str]  # after the keys, when off

    def setup(self, ctx, records, state) -> None:
        self.applies = bool(records)
        self.settle = self.on and CHOICE_OPTIONS[self.name](self.settings.choice_value(
            self.name))
        state = state or {}
        self.share = float(state["share"][0]) if "share" in state else 1.0
        self.paths = restored_paths(state, sorted(records))
        self._say()
        if self.on:
            for r in records.values():
                r.decays = False

    def _say(self) -> None:
        self.why = f"{', '.join(sorted(self.paths))} {self.why_on if self.on else self.why_off}"
        if self.settle:
            self.why += (f"; settle: the full rate only while they move steadily, then a "
                         f"share that halves after each window of {WINDOW} steps in which they "
                         f"only jitter (now {self.share:.3g})")

    def rate(self, record, rate: float) -> float:
        return rate * self.share if self.settle else rate

    def before_render(self, ctx) -> dict[str, object]:
        # theta_{i-1} and the rate it was stepped with: the group's path so far
        if not self.settle or any(ctx.value(k) is None for k in self.paths):
            return {}
        for k, path in self.paths.items():
            path.add(ctx.latent(k), ctx.rate(k))
        if all(p.settled() for p in self.paths.values()):
            self.share = max(FLOOR, self.share * SHRINK)
            for p in self.paths.values():  # the next decision on a window of its own
                p.values, p.rates = [], []
            self._say()
        return {}

    def state(self):
        return {"share": np.array([self.share]), **paths_state(self.paths)}
