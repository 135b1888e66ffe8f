"""What medium_constant_rate and roughness_constant_rate share: their variables step at their
full rate to the job's end, where the schedule's decay (optimize.schedule_factor) would stop
them short of a valley's bottom. Each says which variables, and why the decay costs there."""

from __future__ import annotations

from typing import ClassVar

from .base import Choice


class ConstantRate(Choice):
    writes = ("decays",)
    why_on: ClassVar[str]   # after the keys, when on: what the decay would cost
    why_off: ClassVar[str]  # after the keys, when off

    def setup(self, ctx, records, state) -> None:
        self.applies = bool(records)
        self.why = f"{', '.join(sorted(records))} {self.why_on if self.on else self.why_off}"
        if self.on:
            for r in records.values():
                r.decays = False
