"""What a choice is: one named special case of the optimization loop (optimize.py), with the
state it declares and the hooks the loop calls, as an integrator of Mitsuba's
``ad/integrators/common.py`` implements ``sample()`` for the one shared rendering loop.

The loop, per iteration i (each hook called on every choice in force, in registry order)::

    changed = before_render(loop, i)            # e.g. the next coarse-to-fine level
    for each sensor with a reference:
        images = render(theta_i)                 # the job's integrator, spp, seed
        images = on_images(loop, sensor, images) # e.g. times the exposure gain
        L += loss(images, reference)
    L_step = L + sum(on_loss(loop))              # terms that steer the step only (smoothness)
    backward(L_step)
    on_gradient(loop, i, sensors)                # e.g. eta's derivative by differences
    (the loop's guards: non-finite components zeroed)
    Adam step
    after_step(loop, i)                          # e.g. the gains' clip

and, between Adam's variable u and the value v the scene renders, a chain of maps that the
choices in force contribute (``encode`` v -> u at the start; ``expand``, u at the parameter's
full shape, then ``decode`` u -> v, elementwise, both differentiable, at every update;
``bounds``: the range u is clipped to after a step; ``variable``: Adam's variable for u where
its layout is not the scene's). Without any choice the
loop is Mitsuba's plain Adam loop: u = v, clipped to the parameter's range.

A choice declares its state in ``state`` (plain arrays), which goes into the job's checkpoint
and comes back through ``setup(loop, state)``: a job restored on another worker goes on with
the same choices as it left (a depth measured once is not measured again). Its hooks are timed
by the loop; their seconds per iteration are what the job's status reports as its cost.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from ...engine_api import JobSettings
from ..diagnosis import Kept

if TYPE_CHECKING:  # the loop, for annotations only
    from ..optimize import Optimization

State = dict[str, np.ndarray]


class Choice:
    """A special case of the loop. ``on`` is whether the job's settings leave it on; ``setup``
    sets ``applies`` (does it concern this job at all?) and ``why`` (in words, what it does here
    and why), whether on or not: a choice turned off is listed with what it would have done."""

    name: ClassVar[str]
    # False: a setting of the job asks for it (fit_exposure, a smoothness weight), so it is not
    # turned off by JobSettings.choices but by that setting.
    switchable: ClassVar[bool] = True
    # True: the loop keeps this iteration's renders, detached, in ``loop.images``.
    wants_images: ClassVar[bool] = False

    def __init__(self, settings: JobSettings) -> None:
        self.settings = settings
        self.on = settings.choice_on(self.name) if self.switchable else True
        self.applies = False
        self.why = ""
        self.seconds = 0.0        # its hooks' time (per-iteration hooks only)
        self.setup_seconds = 0.0  # its setup's time

    # -- at the start ----------------------------------------------------------------------

    def prepare_scene(self, loaded, loading):
        """The job's scene before its references are read and the loop is built (another
        scene in its place, e.g. loaded from a rewritten XML); ``loading``: filter_scaling's
        Loading. Sets ``applies`` and ``why`` for a choice that acts here."""
        return loaded

    def setup(self, loop: Optimization, state: State | None) -> None:
        """Decides ``applies`` and ``why``; when on, prepares what the loop needs (starts,
        variables, the integrator's depth). ``state``: what ``state()`` returned before a
        checkpoint, or None on a fresh start."""

    def begin(self, loop: Optimization) -> None:
        """Once Adam's variables hold the start and the scene shows it, before the integrator
        is made: work that renders (a measurement) goes here."""

    # -- between Adam's variable and the scene's value -------------------------------------

    def variable(self, key: str, latent: np.ndarray):
        """Adam's variable for u (flat, the parameter's full shape), when this choice lays it
        out otherwise than the scene's value (coarse to fine); None: as the scene's."""
        return None

    def expand(self, key: str, latent):
        """u at the parameter's full shape, differentiable (a coarse level blown up)."""
        return latent

    def encode(self, key: str, value: np.ndarray) -> np.ndarray:
        """The start value v (flat) as the variable u this choice steps on."""
        return value

    def decode(self, key: str, latent):
        """v from u, differentiable (Dr.Jit)."""
        return latent

    def bounds(self, key: str, lo: float, hi: float) -> tuple[float, float]:
        """The range u is clipped to, given the range so far."""
        return lo, hi

    def kept(self, key: str, kept: Kept) -> Kept:
        """What the diagnosis reads of the parameter (the range its value is kept in, the
        floor it is shown at, whether it is stepped in log space), given what it was so far."""
        return kept

    # -- per iteration ---------------------------------------------------------------------

    def before_render(self, loop: Optimization, i: int) -> bool:
        """Before iteration i renders; True when it changed a variable (the scene is then
        updated)."""
        return False

    def on_images(self, loop: Optimization, sensor: int, images: list) -> list:
        """A sensor's renders as the loss compares them."""
        return images

    def on_loss(self, loop: Optimization):
        """A term added to the loss that the step descends (not the loss recorded); 0: none."""
        return 0.0

    def on_gradient(self, loop: Optimization, i: int, sensors: list[tuple[int, int]]) -> None:
        """After the backward pass of ``sensors`` ((slot, sensor) pairs), before the guards
        and the step: may set gradients (dr.set_grad on loop.opt[key])."""

    def after_step(self, loop: Optimization, i: int) -> None:
        """After Adam's step, before the scene is updated."""

    # -- state -----------------------------------------------------------------------------

    def state(self) -> State:
        """What a restored job needs to go on as this one would have."""
        return {}

    def notes(self) -> list[str]:
        """Lines for the job's notes, per parameter where it matters (said once, at start)."""
        return []


def overrides(choice: Choice, hook: str) -> bool:
    """Whether the choice's class implements ``hook`` (the loop calls only those)."""
    return getattr(type(choice), hook) is not getattr(Choice, hook)
