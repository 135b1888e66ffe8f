"""Choosing the differentiable integrator from the scene and the selected parameters, so a job
pays only for what it needs, and saying why."""

from __future__ import annotations

import re
from dataclasses import dataclass

import mitsuba as mi

from .scene import has_media

DEFAULT_MAX_DEPTH = 8
UNBOUNDED = -1
_GEOMETRY = ("vertex_positions", "to_world")


@dataclass
class Chosen:
    """The integrator a job renders with, why, and its depth (the scene's own until the depth
    choice cuts it) with where that came from."""

    name: str
    why: str
    max_depth: int
    depth_origin: str

    @property
    def has_depth(self) -> bool:
        return self.name != "direct_projective"

    def reason(self) -> str:
        if not self.has_depth:
            return f"{self.why}; the scene renders direct light only"
        shown = "unbounded" if self.max_depth < 0 else self.max_depth
        return f"{self.why}; max_depth {shown} ({self.depth_origin})"


def scene_depth(scene: mi.Scene) -> tuple[int, str]:
    """The scene's own integrator depth (UNBOUNDED for -1 or none), so the optimized image
    matches the scene's look."""
    m = re.search(r"max_depth\s*=\s*(-?\d+)", str(scene.integrator()))
    if not m:
        return DEFAULT_MAX_DEPTH, "default"
    depth = int(m.group(1))
    return (UNBOUNDED if depth < 0 or depth >= 2**31 - 1 else depth), "the scene's"


def choose(scene: mi.Scene, selected: list[str]) -> Chosen:
    depth, origin = scene_depth(scene)
    geometry = [k for k in selected if k.endswith(_GEOMETRY)]
    if has_media(scene):
        return Chosen("prbvolpath", "the scene has participating media", depth, origin)
    if geometry:
        # Projective sampling of visibility edges is costly (prb_projective: ~30x prb on a
        # CPU); a scene that only needs direct light gets the much cheaper direct_projective.
        direct = str(scene.integrator()).startswith("Direct") or 0 < depth <= 2
        return Chosen("direct_projective" if direct else "prb_projective",
                      f"{geometry[0]} moves visibility edges, which needs projective sampling",
                      depth, origin)
    return Chosen("prb", "surface materials only: prb is the cheapest unbiased choice", depth,
                  origin)


def make(name: str, max_depth: int) -> mi.Integrator:
    props = {"type": name} if name == "direct_projective" else {"type": name,
                                                               "max_depth": max_depth}
    return mi.load_dict(props)


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
