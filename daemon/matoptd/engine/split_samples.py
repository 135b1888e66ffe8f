"""Two independent estimates of a render, or of its derivative, from one pass of Mitsuba's
RB integrators (prb, prb_basic, prbvolpath: ``mi.ad.integrators.common.RBIntegrator``).

The standard errors (jacobian.py) estimate each column of J twice from independent
samples, so that J's own noise drops out of the products across the two. One pass at 2s
samples per pixel gives both: each lane is splatted into one of two films by its sample index
within its pixel (the first s into A, the others into B), and the films are developed apart,
as two renders at s spp would be. What is shared is what small images are made of: tracing and
launching. RBIntegrator's forward mode is a primal pass, then a forward pass that replays the
primal's samples reading its radiance (``render_forward``); the primal is the same for every
tangent of a round, so it runs once, and each tangent then costs one forward pass:

    d I_A / d theta . t,  d I_B / d theta . t  =  split(forward(rays, state = primal(rays), t))

Its samples come from an independent sampler, whatever the scene's: the two halves of a
stratified sampler's samples in a pixel are negatively correlated, and a product across A and
B would then underestimate J^T J.

``Frozen`` holds the same passes as frozen functions (``dr.freeze``): once a job's own
iterations replay, Python tracing the integrator pass after pass was most of J's time on
small images.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np
from mitsuba.ad.integrators.common import ADIntegrator, RBIntegrator

from . import frozen


def shares_primal(integrator: mi.Integrator) -> bool:
    """Whether the integrator's forward mode is RBIntegrator's (the projective integrators add
    boundary terms of their own, rendered apart)."""
    # by name: Mitsuba's AD integrators imported again (another module's import of them)
    # make classes of their own, whose methods are not RBIntegrator's objects
    method = type(integrator).render_forward
    return (method is RBIntegrator.render_forward
            or getattr(method, "__qualname__", "") == "RBIntegrator.render_forward")


@dataclass
class Traced:
    """One sensor's camera rays at 2s spp, their primal pass, and which lanes are estimate A."""

    film: Any
    sampler: Any      # as left by the rays: each pass replays it from a clone
    ray: Any
    weight: Any
    pos: Any
    first: Any        # mi.Bool: the lane is one of the first s samples of its pixel
    radiance: Any     # the primal's L, which the forward pass reads (state_in)
    valid: Any
    sensor: int = 0   # what a frozen pass traces again (Frozen.trace; the rest None)
    spp: int = 0
    seed: int = 0


@functools.cache
def _independent() -> mi.Sampler:
    return mi.load_dict({"type": "independent"})


def _rays(scene: mi.Scene, integrator: mi.Integrator, sensor: int, spp: int, seed):
    """The film, the sampler as the rays leave it, the rays, their weights and film positions,
    and which lanes are estimate A, of 2 * ``spp`` samples per pixel."""
    camera = scene.sensors()[sensor]
    film = camera.film()
    total = 2 * spp
    sampler = _independent().clone()
    sampler.set_sample_count(total)
    sampler.set_samples_per_wavefront(total)
    size = film.crop_size()
    if film.sample_border():
        size += 2 * film.rfilter().border_size()
    lanes = int(dr.prod(size)) * total
    sampler.seed(seed, lanes)
    film.prepare(integrator.aov_names())
    ray, weight, pos = integrator.sample_rays(scene, camera, sampler)
    # opaque: literals would make each spp's primal kernel a kernel of its own to compile
    first = (dr.arange(mi.UInt32, lanes) % dr.opaque(mi.UInt32, total)
             < dr.opaque(mi.UInt32, spp))
    return film, sampler, ray, weight, pos, first


def _sample(scene: mi.Scene, integrator: mi.Integrator, sampler, ray, radiance=None):
    """The primal pass (``radiance`` None) or the forward pass that replays it: L or dL, and
    which lanes are valid."""
    value, valid, _, _ = integrator.sample(
        mode=dr.ADMode.Primal if radiance is None else dr.ADMode.Forward, scene=scene,
        sampler=sampler.clone(), ray=ray, depth=mi.UInt32(0), δL=None, δaovs=None,
        state_in=radiance, active=mi.Bool(True))
    return value, valid


def trace(scene: mi.Scene, integrator: mi.Integrator, sensor: int, spp: int,
          seed: int) -> Traced:
    """The rays and primal pass of 2 * ``spp`` samples per pixel, evaluated once."""
    with dr.suspend_grad():
        film, sampler, ray, weight, pos, first = _rays(scene, integrator, sensor, spp, seed)
        radiance, valid = _sample(scene, integrator, sampler, ray)
        dr.eval(ray, weight, pos, radiance, valid, first)
    return Traced(film, sampler, ray, weight, pos, first, radiance, valid)


def primal(t: Traced, integrator: mi.Integrator) -> tuple[np.ndarray, np.ndarray]:
    """The two renders (H, W, 3) of the traced primal pass."""
    with dr.suspend_grad():
        return _arrays(_split(t.film, t.first, t.pos, t.weight, t.ray, integrator, t.radiance,
                              t.valid))


def forward(t: Traced, scene: mi.Scene, integrator: mi.Integrator
            ) -> tuple[np.ndarray, np.ndarray]:
    """The two estimates (H, W, 3) of the render's derivative along the tangents the caller
    set on the scene's parameters (dr.set_grad and a forward traversal, as for
    ``render_forward``), replaying the traced samples."""
    with dr.suspend_grad():
        tangent, valid = _sample(scene, integrator, t.sampler, t.ray, t.radiance)
        return _arrays(_split(t.film, t.first, t.pos, t.weight, t.ray, integrator, tangent,
                              valid))


class Frozen:
    """The same passes as frozen functions (``dr.freeze``), recorded once per sensor and spp
    and replayed for every seed and tangent: J's passes are mostly Python tracing the
    integrator on small images. What a replay must see fresh enters as an argument: the seed
    (an opaque mi.UInt32: a Python int is part of a recording's key), the primal's radiance,
    the leaves and their tangents (set on the leaves inside, where the forward pass begins).
    The rays are traced again inside each pass rather than passed in (a film or a sampler
    cannot be a frozen function's output); they are a small part of a pass."""

    def __init__(self) -> None:
        self._primal, self._radiance, self._inside, self._forward = (
            frozen.freeze(f) for f in (_primal_pass, _radiance_pass, _inside_pass, _forward_pass))
        self.inside = True  # the tangents set inside the forward pass (until that fails)

    @property
    def recordings(self) -> int:
        return sum(f.n_recordings for f in (self._primal, self._radiance, self._inside,
                                            self._forward))

    def trace(self, scene: mi.Scene, integrator: mi.Integrator, sensor: int, spp: int,
              seed: int) -> Traced:
        """As ``trace``: what a forward pass replays (its radiance and seed)."""
        radiance = frozen.call(self._radiance, scene, integrator, sensor, spp, _opaque(seed))
        return Traced(None, None, None, None, None, None, radiance, None, sensor, spp, seed)

    def primal(self, scene: mi.Scene, integrator: mi.Integrator, sensor: int, spp: int,
               seed: int) -> tuple[np.ndarray, np.ndarray]:
        """As ``primal(trace(...))``: the two renders."""
        return _arrays(frozen.call(self._primal, scene, integrator, sensor, spp,
                                   _opaque(seed)))

    def forward(self, t: Traced, scene: mi.Scene, params: mi.SceneParameters,
                integrator: mi.Integrator, leaves: list[str], directions: list
                ) -> tuple[np.ndarray, np.ndarray]:
        """As ``forward`` along ``directions``, the tangents of the scene's ``params``
        ``leaves`` (keys), set inside the recording, so that its key stays that of the first
        pass. Where the plugins derive values from a leaf at update() (a texture's data), the
        edges from it lie outside the recording, which may not follow them: the tangents are
        then carried to those values outside, and the pass replays what they hold."""
        args = (integrator, t.sensor, t.spp, _opaque(t.seed), t.radiance)
        if self.inside:
            try:
                return _arrays(frozen.call(self._inside, scene, params, *args, leaves,
                                           directions))
            except RuntimeError as exc:
                while exc.__cause__ is not None:
                    exc = exc.__cause__
                if "lies outside" not in str(exc):  # an edge made before the recording
                    raise
                self.inside = False
        tangents([params[key] for key in leaves], directions)
        return _arrays(frozen.call(self._forward, scene, *args))


def _opaque(seed: int):
    return dr.opaque(mi.UInt32, seed)


def _radiance_pass(scene, integrator, sensor, spp, seed):
    with dr.suspend_grad():
        _, sampler, ray, _, _, _ = _rays(scene, integrator, sensor, spp, seed)
        return _sample(scene, integrator, sampler, ray)[0]


def _primal_pass(scene, integrator, sensor, spp, seed):
    with dr.suspend_grad():
        film, sampler, ray, weight, pos, first = _rays(scene, integrator, sensor, spp, seed)
        radiance, valid = _sample(scene, integrator, sampler, ray)
        return _split(film, first, pos, weight, ray, integrator, radiance, valid)


def tangents(leaves: list, directions: list) -> None:
    """Each leaf's tangent set and carried forward to what depends on it (a forward pass's
    start, as for ``render_forward``)."""
    for leaf, direction in zip(leaves, directions):
        dr.set_grad(leaf, direction)
        dr.enqueue(dr.ADMode.Forward, leaf)
    dr.traverse(dr.ADMode.Forward, dr.ADFlag.ClearEdges)


def _inside_pass(scene, params, integrator, sensor, spp, seed, radiance, leaves, directions):
    tangents([params[key] for key in leaves], directions)
    return _forward_pass(scene, integrator, sensor, spp, seed, radiance)


def _forward_pass(scene, integrator, sensor, spp, seed, radiance):
    with dr.suspend_grad():
        film, sampler, ray, weight, pos, first = _rays(scene, integrator, sensor, spp, seed)
        tangent, valid = _sample(scene, integrator, sampler, ray, radiance)
        return _split(film, first, pos, weight, ray, integrator, tangent, valid)


def _arrays(images) -> tuple[np.ndarray, np.ndarray]:
    return tuple(np.array(image, dtype=np.float64)[..., :3] for image in images)


def _split(film, first, pos, weight, ray, integrator: mi.Integrator, value, valid) -> list:
    images = []
    value = value * weight
    plain = mi.is_rgb and not mi.has_flag(film.flags(), mi.FilmFlags.Special)
    for lanes in (first, ~first):
        film.prepare(integrator.aov_names())  # a fresh film for each estimate
        block = film.create_block()
        block.set_coalesce(False)  # a lane's neighbours may go to the other film
        if plain:  # RGB channels, [alpha,] weight, as _splat_to_block puts them
            alpha = [dr.select(valid, mi.Float(1), mi.Float(0))] if mi.has_flag(
                film.flags(), mi.FilmFlags.Alpha) else []
            block.put(pos, [value.x, value.y, value.z, *alpha, mi.Float(1)], active=lanes)
        else:  # the other lanes put with weight 0: the same image, at twice the splats
            share = dr.select(lanes, mi.Float(1), mi.Float(0))
            ADIntegrator._splat_to_block(block, film, pos, value=value * share,
                                         weight=share, alpha=dr.select(valid, share, 0),
                                         aovs=[], wavelengths=ray.wavelengths)
        film.put_block(block)
        images.append(film.develop())  # reads this film's storage, not the next one's
    dr.eval(*images)  # both in one launch
    return images
