"""A job's choices as the loop meets them: each selects its variables and sets up (with its
state from a checkpoint), and those in force are called at the loop's fixed points, each
timed on its own: what the job's status reports as a choice's cost."""

from __future__ import annotations

import time

from .. import engine_api as api
from .choices import Begun, Choice, assign_keys, overrides
from .records import ParamRecord

STEP_HOOKS = ("before_render", "on_images", "on_loss", "on_gradient")


class Hooks:
    def __init__(self, ctx, choices: list[Choice], records: dict[str, ParamRecord],
                 states: dict[str, dict] | None) -> None:
        """``states``: each choice's state by name from a checkpoint (None: a fresh start)."""
        self.ctx, self.choices = ctx, choices
        for c in choices:
            records.update({r.key: r for r in c.variables(ctx)})
        assign_keys(ctx, choices, records)
        for c in choices:
            state = None if states is None else states.get(c.name, {})
            self.timed(c, "setup_seconds", c.setup, ctx, {k: records[k] for k in c.keys},
                       state)
        self.active = [c for c in choices if c.on and c.applies]
        self.by_hook = {h: [c for c in self.active if overrides(c, h)] for h in STEP_HOOKS}
        self.wants_images = any(c.wants_images for c in self.active)

    @staticmethod
    def timed(c: Choice, clock: str, hook, *args):
        began, out = time.perf_counter(), hook(*args)
        setattr(c, clock, getattr(c, clock) + time.perf_counter() - began)
        return out

    def call(self, hook: str, *args) -> list:
        """``hook`` on every choice in force that has it, in order."""
        return [self.timed(c, "seconds", getattr(c, hook), self.ctx, *args)
                for c in self.by_hook[hook]]

    def on_images(self, sensor: int, images: list) -> list:
        for c in self.by_hook["on_images"]:
            images = self.timed(c, "seconds", c.on_images, self.ctx, sensor, images)
        return images

    def begin(self) -> Begun | None:
        """Each choice's work at the start that renders; the last depth one returned."""
        out = None
        for c in self.active:
            if overrides(c, "begin"):
                out = self.timed(c, "setup_seconds", c.begin, self.ctx) or out
        return out

    def status(self, iterations: int) -> list[api.ChoiceStatus]:
        """The choices that concern the job, on or off, with their measured cost."""
        n = max(1, iterations)
        return [api.ChoiceStatus(c.name, c.on, c.why, c.seconds / n, c.setup_seconds,
                                 c.switchable) for c in self.choices if c.applies]
