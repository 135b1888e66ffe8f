"""Frozen iterations: each sensor group's render, loss and backward pass recorded once per
structure with ``dr.freeze`` and replayed (engine/frozen.py); the Adam step, the guards and
the other choices' hooks stay outside, as in the unfrozen loop, with the same results.

Where Python's tracing is most of an iteration (small films, few sensors' worth of work) a
replay saves most of it; the first iteration of each structure records and costs more than
an unfrozen one. A job falls back to the unfrozen loop, and its notes say why, where its
scene or parameters cannot be frozen (moving geometry, a projective integrator) or where a
choice in force maps the renders themselves (exposure gains). A choice that reads the
iteration's renders (eta by differences) gets them from the recording, and its own renders
at other values are replayed too (engine/frozen.py).
"""

from __future__ import annotations

from .. import frozen
from .base import Choice


class Frozen(Choice):
    name = "frozen"

    def select(self, ctx, records):
        return [k for k, r in records.items() if r.scene is not None]

    def setup(self, ctx, records, state) -> None:
        self.applies = True
        self.reason = frozen.unfreezable(ctx.chosen.name,
                                         {k: r.kind for k, r in records.items()})
        self._say()

    def begin(self, ctx):
        hooks = ctx.render_hooks
        if hooks and not self.reason:
            self.reason = (f"{', '.join(hooks)} map the renders themselves, outside what is "
                           "recorded")
            self._say()

    def _say(self) -> None:
        self.why = (f"not frozen: {self.reason}" if self.reason else
                    "each sensor group's render, loss and backward pass recorded once per "
                    "structure (spp, integrator, film size) and replayed, as are "
                    "eta's difference renders and the standard errors' passes: no Python "
                    "tracing per iteration")

    def group_loss(self, ctx):
        if self.reason:
            return None
        group = frozen.FrozenLoss(ctx)
        if group.taken:
            self.why += ("; the scene's recording from a job before is taken over (replayed "
                         "from iteration 0 for a structure a job before ran: the same spp, "
                         "integrator and films)")
        return group

    def notes(self) -> list[str]:
        return [f"frozen: {self.why}"]
