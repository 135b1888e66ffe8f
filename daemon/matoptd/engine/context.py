"""What a choice sees of its job: the settings, the scene and its references, and per
iteration what the loop has made so far. Choices get this and their own records, never the
loop: what they may read and do is listed here, once.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .. import engine_api as api
from .diagnosis import Kept
# at import, not inside an iteration: imported there first, Mitsuba's AD integrators module
# made that iteration's J draw other samples than every later one
from .jacobian import Job, Linearization, Quantity, linearize, references

if TYPE_CHECKING:
    from .integrator import Chosen
    from .optimize import Optimization
    from .renders import Reference


class Context:
    """The job (``settings``, ``scene``, ``params``, ``references``, ``chosen``: the
    integrator, read-only) and the iteration under way: ``iteration``, ``spp``, ``sensors``
    ((slot, sensor) pairs whose loss the step descends), ``images`` (this iteration's renders,
    detached, for a choice that ``wants_images``) and ``held`` (keys a hook held this step)."""

    def __init__(self, loop: Optimization) -> None:
        self._loop = loop
        self.settings: api.JobSettings = loop.settings
        self.iteration = 0
        self.sensors: list[tuple[int, int]] = []
        self.images: dict[int, list] = {}
        self.held: set[str] = set()

    @property
    def scene(self):
        return self._loop.renders.scene

    @property
    def params(self):
        return self._loop.renders.params

    @property
    def references(self) -> dict[int, Reference]:
        return self._loop.renders.references

    @property
    def chosen(self) -> Chosen:
        return self._loop.chosen

    @property
    def spp(self) -> int:
        return self._loop.spp

    @property
    def integrator(self):
        """The integrator the loss's renders use (made once the choices have begun)."""
        return self._loop.renders.integrator

    @property
    def shelf(self) -> dict[str, object]:
        """What the job takes over from the jobs before on its scene and leaves for the next
        (kept_scenes.Loaded.shelf; empty for a scene loaded for the job alone)."""
        return self._loop.shelf

    @property
    def loss(self):
        """The job's loss (losses.py)."""
        return self._loop.loss

    @property
    def keeps_images(self) -> bool:
        """Whether a choice in force reads ``images``."""
        return self._loop.hooks.wants_images

    @property
    def render_hooks(self) -> list[str]:
        """The choices in force that map a sensor's renders (by name)."""
        loop = self._loop
        return [c.name for c in loop.active if c in loop.hooks.by_hook["on_images"]]

    def note(self, line: str) -> None:
        """A line for the job's notes, said during the job (reported at its end)."""
        self._loop.said.append(line)

    @property
    def initial(self) -> dict[str, np.ndarray]:
        """theta_0, once the loop has read it."""
        return self._loop.initial

    # -- the variables ----------------------------------------------------------------------

    def variable(self, key: str):
        """Adam's variable of ``key`` (differentiable)."""
        return self._loop.opt[key]

    def decoded(self, key: str, latent):
        """v from u at u's own shape (elementwise maps only)."""
        return self._loop.maps.decode(key, latent)

    def latent(self, key: str) -> np.ndarray:
        """theta_i's value of ``key`` in the space it is stepped in."""
        return self._loop.maps.encode(key, self._loop.records[key].current)

    def encoded(self, key: str, value: np.ndarray) -> np.ndarray:
        """u of a value v of ``key`` (flat), as the maps in force encode it."""
        return self._loop.maps.encode(key, value)

    def kept(self, key: str) -> Kept:
        """The range ``key``'s value is kept in, its floor, whether it is stepped in log space."""
        return self._loop.maps.kept(self._loop.records[key])

    def value(self, key: str) -> np.ndarray:
        """theta_i's value of ``key`` (v)."""
        return self._loop.records[key].current

    def rate(self, key: str) -> float:
        """The rate of ``key`` at this step (its step rate times the schedule's share)."""
        return self._loop.rate(key)

    # -- renders ----------------------------------------------------------------------------

    def holding(self, values: dict[str, np.ndarray]):
        """The scene with these parameters set to ``values`` for a while (a context)."""
        return self._loop.renders.holding(values)

    def seeds(self, n: int) -> list[int]:
        """This iteration's render seeds of slot n's sensor."""
        return self._loop.renders.seeds(self.iteration, n)

    def sensor_images(self, n: int, sensor: int, draw: int = 0, spp: int | None = None
                      ) -> list:
        """This iteration's renders of a sensor as the loss compares them; ``draw`` picks
        other samples."""
        return self._loop.renders.sensor_images(self.iteration, n, sensor, draw,
                                                spp or self.spp)

    def image_loss(self, images: list, sensor: int):
        """The loss of renders against a sensor's reference."""
        return self._loop.renders.image_loss(images, self.references[sensor])

    def linearize(self, quantities: list[Quantity], seed: int) -> Linearization:
        """J of the renders in ``quantities`` (and the render noise and misfit) at the values
        the scene shows, at this iteration's spp, from samples drawn by ``seed``, in one round
        whatever the time (jacobian.linearize)."""
        loop = self._loop
        gains = {r.sensor: r.current for r in loop.records.values() if r.is_gain}
        job = Job(self.settings.loss, self.spp, seed, self.settings.clamp, 0.0)
        return linearize(self.scene, self.params, self.integrator, self.chosen.name,
                         quantities, references(self.references, gains), job, fixed=True)

    def render(self, values: dict[str, np.ndarray], sensor: int, spp: int) -> np.ndarray:
        """A primal render with the parameters set to ``values`` (numpy, off the graph)."""
        return self._loop.renders.render(values, sensor, spp)
