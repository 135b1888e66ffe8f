"""What a choice is: one named special case of the optimization loop (optimize.py), with the
state it declares and the hooks the loop calls, as an integrator of Mitsuba's
``ad/integrators/common.py`` implements ``sample()`` for the one shared rendering loop.

A choice sees the job through a ``Context`` (context.py) and its own records: ``select``
names the variables it concerns, and every per-variable hook is called for those alone. Hooks
return what they change; the loop applies it. The loop, per iteration i::

    changed = before_render(ctx)                  # {key: Adam variable}: e.g. a finer level
    for each sensor with a reference:
        images = render(theta_i)                  # the job's integrator, spp, seed
        images = on_images(ctx, sensor, images)   # e.g. times the exposure gain
        L += loss(images, reference)
    L_step = L + sum(on_loss(ctx))                # terms that steer the step only (smoothness)
    backward(L_step)
    gradients = on_gradient(ctx)                  # {key: gradient or HOLD}: eta by differences
    (the loop's guards: non-finite components zeroed)
    Adam step, each u clipped to its bounds

and, between Adam's variable u and the value v the scene renders, a chain of maps the choices
contribute for their keys (``encode`` v -> u at the start; ``expand``, u
at the parameter's full shape, then ``decode`` u -> v, elementwise, both differentiable;
``bounds``: the range u is clipped to; ``rate``: a step's base rate; ``variable``: Adam's
variable for u where its layout is not the scene's). Without any choice the loop is Mitsuba's
plain Adam loop: u = v, clipped to the parameter's range.

Choices never read one another. Where two meet, they say so, and the registry checks it:
``after`` (this one's hooks run after those), ``yields_to`` (a key one of those selects, when
on, is not this one's) and ``excludes`` (not on beside those for the same key).

A choice declares its state in ``state`` (plain arrays), which goes into the job's checkpoint
and comes back through ``setup(ctx, records, state)``: a job restored on another worker goes
on with the same choices as it left. Its hooks are timed by the loop; their seconds per
iteration are what the job's status reports as its cost.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, Iterable

import numpy as np

from ...engine_api import JobSettings
from ..diagnosis import Kept
from ..records import ParamRecord

if TYPE_CHECKING:  # annotations only
    from ..context import Context

State = dict[str, np.ndarray]
HOLD = "hold"  # on_gradient's value for a key whose step is held (no step, Adam's state kept)


@dataclass
class Begun:
    """What a choice's ``begin`` changes of the job: the integrator's depth, and why."""

    max_depth: int
    origin: str


class Choice:
    """A special case of the loop. ``on`` is whether the job's settings leave it on; ``setup``
    sets ``applies`` (does it concern this job at all?) and ``why`` (in words, what it does here
    and why), whether on or not: a choice turned off is listed with what it would have done."""

    name: ClassVar[str]
    # False: a setting of the job asks for it (fit_exposure, a smoothness weight), so it is not
    # turned off by JobSettings.choices but by that setting.
    switchable: ClassVar[bool] = True
    # True: the loop keeps this iteration's renders, detached, in ``ctx.images``.
    wants_images: ClassVar[bool] = False
    after: ClassVar[tuple[str, ...]] = ()
    yields_to: ClassVar[tuple[str, ...]] = ()
    excludes: ClassVar[tuple[str, ...]] = ()
    # Fields of its own records that its ``setup`` may write (black_start: the start); the
    # loop reads the records after every setup.
    writes: ClassVar[tuple[str, ...]] = ()

    def __init__(self, settings: JobSettings) -> None:
        self.settings = settings
        self.on = settings.choice_on(self.name) if self.switchable else True
        self.applies = False
        self.why = ""
        self.keys: list[str] = []    # the variables it concerns (``select``)
        self.adam_uniform = False    # True: Adam in its uniform mode (one per optimizer)
        self.adam_beta_1: float | None = None  # Adam's beta_1 (one per optimizer); None: 0.9
        self.seconds = 0.0           # its hooks' time (per-iteration hooks only)
        self.setup_seconds = 0.0     # its setup's time

    # -- at the start ----------------------------------------------------------------------

    def prepare_scene(self, loaded, loading):
        """The job's scene before its references are read and the loop is built (another
        scene in its place, e.g. loaded from a rewritten XML); ``loading``: filter_scaling's
        Loading. Sets ``applies`` and ``why`` for a choice that acts here."""
        return loaded

    def select(self, ctx: Context, records: dict[str, ParamRecord]) -> Iterable[str]:
        """The keys of the variables this choice concerns, from all of the job's."""
        return ()

    def setup(self, ctx: Context, records: dict[str, ParamRecord], state: State | None
              ) -> None:
        """Decides ``applies`` and ``why`` from its own ``records``; when on, prepares what it
        needs, and may narrow ``keys`` to those its maps act on. ``state``: what ``state()``
        returned before a checkpoint, or None on a fresh start."""

    def variables(self, ctx: Context) -> list[ParamRecord]:
        """Variables of its own that Adam steps beside the parameters (exposure gains)."""
        return []

    def begin(self, ctx: Context) -> Begun | None:
        """Once Adam's variables hold the start and the scene shows it, before the integrator
        is made: work that renders (a measurement) goes here."""
        return None

    # -- between Adam's variable and the scene's value (its own keys only) ------------------

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

    def rate(self, record: ParamRecord, rate: float) -> float:
        """The base rate of the next step (before the schedule's share), given the rate so far;
        ``record.current`` holds theta_{i-1}'s value."""
        return rate

    # -- per iteration ---------------------------------------------------------------------

    def before_render(self, ctx: Context) -> dict[str, object]:
        """Before iteration ``ctx.iteration`` renders: Adam variables it replaces, by key."""
        return {}

    def on_images(self, ctx: Context, sensor: int, images: list) -> list:
        """A sensor's renders as the loss compares them."""
        return images

    def on_loss(self, ctx: Context):
        """A term added to the loss that the step descends (not the loss recorded); 0: none."""
        return 0.0

    def group_loss(self, ctx: Context):
        """Once, after ``begin``: an object that takes over the loop's render, loss and backward
        pass for a group of sensors (engine/frozen.py's ``FrozenLoss``: ``leaf``, a call,
        ``backward``); None: the loop renders itself."""
        return None

    def on_gradient(self, ctx: Context) -> dict[str, object]:
        """After the backward pass of ``ctx.sensors``, before the guards and the step: the
        gradients it sets (a Dr.Jit value), or HOLD for a step not taken, by key."""
        return {}

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


class ConflictError(ValueError):
    """Two choices in force that exclude each other concern the same variable."""


def check_declarations(registry: tuple[type[Choice], ...]) -> None:
    """Every name a choice declares is a choice, and ``after`` agrees with the order."""
    order = {c.name: n for n, c in enumerate(registry)}
    for c in registry:
        for what in ("after", "yields_to", "excludes"):
            unknown = [n for n in getattr(c, what) if n not in order]
            if unknown:
                raise ValueError(f"choice {c.name}: {what} names no choice: {unknown}")
        late = [n for n in c.after if order[n] > order[c.name]]
        if late:
            raise ValueError(f"choice {c.name} runs after {late}, which come later in the "
                             "registry")


def assign_keys(ctx: Context, choices: list[Choice], records: dict[str, ParamRecord]
                ) -> None:
    """Each choice's keys: what it selects, less what a choice it yields to (on) selects.
    ConflictError where two choices in force that exclude each other share a key."""
    selected = {c.name: list(dict.fromkeys(c.select(ctx, records))) for c in choices}
    on = {c.name for c in choices if c.on}
    for c in choices:
        taken = {k for other in c.yields_to if other in on for k in selected.get(other, ())}
        c.keys = [k for k in selected[c.name] if k not in taken]
    for c in choices:
        for other in c.excludes:
            shared = sorted(set(c.keys) & set(selected.get(other, ())))
            if c.on and other in on and shared:
                raise ConflictError(
                    f"choices {c.name} and {other} cannot both be on for {', '.join(shared)}; "
                    f"turn one off (choices {c.name}=off or {other}=off)")
