"""Choosing the differentiable integrator from the scene and the selected parameters, so a job
pays only for what it needs, and saying why."""

from __future__ import annotations

import re

import mitsuba as mi

from .scene import has_media

DEFAULT_MAX_DEPTH = 8
# An unbounded depth (-1) is capped for optimization. Russian roulette ends a path by its
# throughput, and with albedo near 1 the throughput hardly falls: in an optically thick medium
# a path can scatter thousands of times, and a symbolic loop runs until its longest lane ends
# (in the adjoint pass as well). 64 bounces keep all but a sliver of the light in the cases of
# bench/stability.py while bounding each iteration's cost.
DEPTH_CAP = 64
_GEOMETRY = ("vertex_positions", "to_world")


def max_depth(scene: mi.Scene) -> tuple[int, str]:
    """The scene's own integrator depth, so the optimized image matches the scene's look."""
    m = re.search(r"max_depth\s*=\s*(-?\d+)", str(scene.integrator()))
    if not m:
        return DEFAULT_MAX_DEPTH, "default"
    depth = int(m.group(1))
    if depth < 0 or depth > DEPTH_CAP:
        shown = "unbounded depth" if depth < 0 or depth >= 2**31 else depth
        return DEPTH_CAP, (f"the scene's {shown} capped: long paths (albedo near 1) would "
                           "make every iteration as slow as its longest path")
    return depth, "the scene's"


def choose(scene: mi.Scene, selected: list[str]) -> tuple[mi.Integrator, str, str]:
    """(integrator, name, reason)."""
    depth, origin = max_depth(scene)
    geometry = [k for k in selected if k.endswith(_GEOMETRY)]
    if has_media(scene):
        name, why = "prbvolpath", "the scene has participating media"
    elif geometry:
        # Projective sampling of visibility edges is costly (prb_projective: ~30x prb on a
        # CPU); a scene that only needs direct light gets the much cheaper direct_projective.
        direct = str(scene.integrator()).startswith("Direct") or 0 < depth <= 2
        name = "direct_projective" if direct else "prb_projective"
        why = f"{geometry[0]} moves visibility edges, which needs projective sampling"
    else:
        name, why = "prb", "surface materials only: prb is the cheapest unbiased choice"
    props = {"type": name} if name == "direct_projective" else {"type": name, "max_depth": depth}
    integrator = mi.load_dict(props)
    if name == "direct_projective":
        return integrator, name, f"{why}; the scene renders direct light only"
    return integrator, name, f"{why}; max_depth {depth} ({origin})"


def medium_notes(scene: mi.Scene, selected: list[str]) -> list[str]:
    """Warnings for selected media properties whose gradient prbvolpath gets wrong.

    A heterogeneous medium samples collisions against a majorant, the largest extinction in it
    (heterogeneous.cpp). With a constant sigma_t the majorant equals sigma_t, so no null
    collision is ever sampled, and the derivative of the transmittance, which prbvolpath
    carries through null collisions, is lost: what is left says that denser is always
    brighter. On the thesis's Table 5 kind sigma_t ran from 0.99 to 1.9 against a truth of
    0.4; the same scene with a homogeneous medium (whose albedo may still be a grid) came
    down toward the truth.
    """
    notes = []
    for shape in scene.shapes():
        for where in ("interior_medium", "exterior_medium"):
            medium = getattr(shape, where)()
            if medium is None or medium.is_homogeneous():
                continue
            prefixes = {f"{shape.id()}.{where}", medium.id()} - {""}
            for key in selected:
                if any(key.startswith(f"{p}.sigma_t.value") for p in prefixes):
                    notes.append(
                        f"{key}: a constant sigma_t in a heterogeneous medium gets a biased "
                        "gradient (with no null collisions prbvolpath misses the "
                        "transmittance's share, so it drifts denser than the images say): a "
                        "homogeneous medium, whose albedo may still be a grid, renders the "
                        "same extinction and differentiates it exactly")
    return sorted(set(notes))
