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
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np
from mitsuba.ad.integrators.common import ADIntegrator, RBIntegrator


def shares_primal(integrator: mi.Integrator) -> bool:
    """Whether the integrator's forward mode is RBIntegrator's (the projective integrators add
    boundary terms of their own, rendered apart)."""
    return type(integrator).render_forward is RBIntegrator.render_forward


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


@functools.cache
def _independent() -> mi.Sampler:
    return mi.load_dict({"type": "independent"})


def trace(scene: mi.Scene, integrator: mi.Integrator, sensor: int, spp: int,
          seed: int) -> Traced:
    """The rays and primal pass of 2 * ``spp`` samples per pixel, evaluated once."""
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
    with dr.suspend_grad():
        ray, weight, pos = integrator.sample_rays(scene, camera, sampler)
        radiance, valid, _, _ = integrator.sample(
            mode=dr.ADMode.Primal, scene=scene, sampler=sampler.clone(), ray=ray,
            depth=mi.UInt32(0), δL=None, state_in=None, active=mi.Bool(True))
        # opaque: literals would make each spp's primal kernel a kernel of its own to compile
        first = (dr.arange(mi.UInt32, lanes) % dr.opaque(mi.UInt32, total)
                 < dr.opaque(mi.UInt32, spp))
        dr.eval(ray, weight, pos, radiance, valid, first)
    return Traced(film, sampler, ray, weight, pos, first, radiance, valid)


def primal(t: Traced, integrator: mi.Integrator) -> tuple[np.ndarray, np.ndarray]:
    """The two renders (H, W, 3) of the traced primal pass."""
    with dr.suspend_grad():
        return _split(t, integrator, t.radiance, t.valid)


def forward(t: Traced, scene: mi.Scene, integrator: mi.Integrator
            ) -> tuple[np.ndarray, np.ndarray]:
    """The two estimates (H, W, 3) of the render's derivative along the tangents the caller
    set on the scene's parameters (dr.set_grad and a forward traversal, as for
    ``render_forward``), replaying the traced samples."""
    with dr.suspend_grad():
        tangent, valid, _, _ = integrator.sample(
            mode=dr.ADMode.Forward, scene=scene, sampler=t.sampler.clone(), ray=t.ray,
            depth=mi.UInt32(0), δL=None, δaovs=None, state_in=t.radiance,
            active=mi.Bool(True))
        return _split(t, integrator, tangent, valid)


def _split(t: Traced, integrator: mi.Integrator, value, valid
           ) -> tuple[np.ndarray, np.ndarray]:
    images = []
    value = value * t.weight
    plain = mi.is_rgb and not mi.has_flag(t.film.flags(), mi.FilmFlags.Special)
    for lanes in (t.first, ~t.first):
        t.film.prepare(integrator.aov_names())  # a fresh film for each estimate
        block = t.film.create_block()
        block.set_coalesce(False)  # a lane's neighbours may go to the other film
        if plain:  # RGB channels, [alpha,] weight, as _splat_to_block puts them
            alpha = [dr.select(valid, mi.Float(1), mi.Float(0))] if mi.has_flag(
                t.film.flags(), mi.FilmFlags.Alpha) else []
            block.put(t.pos, [value.x, value.y, value.z, *alpha, mi.Float(1)], active=lanes)
        else:  # the other lanes put with weight 0: the same image, at twice the splats
            share = dr.select(lanes, mi.Float(1), mi.Float(0))
            ADIntegrator._splat_to_block(block, t.film, t.pos, value=value * share,
                                         weight=share, alpha=dr.select(valid, share, 0),
                                         aovs=[], wavelengths=t.ray.wavelengths)
        t.film.put_block(block)
        images.append(t.film.develop())  # reads this film's storage, not the next one's
    dr.eval(*images)  # both in one launch
    return tuple(np.array(image, dtype=np.float64)[..., :3] for image in images)
