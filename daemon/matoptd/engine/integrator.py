"""The differentiable integrator a job renders with: the scene's own, with its properties
(``max_depth``, ``rr_depth``, ``hide_emitters``, a projective one's ``sppc``/``sppp``/``sppi``
and guiding), whenever it can differentiate the selected parameters; replaced or amended only
where it cannot, and then the job's notes say what and why.

A projective integrator's silhouette sampling is what a moving edge needs, and it dominates
the cost of a step: Mitsuba's own shape example sets ``sppi`` 0 (no indirect silhouettes) on
``direct_projective``, and a step with the default ``sppi`` took 38-51x as long on the same
problem (docs/benchmarks.md, geometry). So such properties stand as the scene sets them.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import mitsuba as mi

from ..settings import INTEGRATORS
from .scene import has_media

DEFAULT_MAX_DEPTH = 8
UNBOUNDED = -1
_GEOMETRY = ("vertex_positions", "to_world")
PROJECTIVE = ("direct_projective", "prb_projective")
# Mitsuba's differentiable integrators by class, and the plugin names of the others it ships
# that a scene may name (their C++ classes print these names).
_PYTHON = {"PRBIntegrator": "prb", "BasicPRBIntegrator": "prb_basic",
           "PRBVolpathIntegrator": "prbvolpath", "DirectProjectiveIntegrator": "direct_projective",
           "PathProjectiveIntegrator": "prb_projective"}
assert set(_PYTHON.values()) == set(INTEGRATORS), "settings.INTEGRATORS"
_NATIVE = {"PathIntegrator": "path", "VolumetricSimplePathIntegrator": "volpath",
           "VolumetricPathIntegrator": "volpath", "VolumetricMisPathIntegrator": "volpathmis",
           "DirectIntegrator": "direct"}
# Properties a projective integrator reads (PSIntegrator and its two plugins); None: unset.
_PROJECTIVE_PROPS = ("sppc", "sppp", "sppi", "guiding", "guiding_proj", "guiding_rounds",
                     "project_seed")


@dataclass
class Own:
    """The scene's integrator as its plugin name and the properties it was given (those this
    module reads); ``name`` "" for none, ``shown`` what it prints as."""

    name: str
    props: dict = field(default_factory=dict)
    shown: str = ""

    @property
    def max_depth(self) -> int | None:
        return self.props.get("max_depth")


def read(scene: mi.Scene) -> Own:
    """The scene's integrator and its properties (max_depth UNBOUNDED for -1)."""
    it = scene.integrator()
    if it is None:
        return Own("")
    text = str(it)
    shown = text.split("[", 1)[0].strip()
    props: dict = {"hide_emitters": bool(it.hide_emitters)}
    name = _PYTHON.get(type(it).__name__, "")
    if name:  # Mitsuba's Python integrators keep their properties as attributes
        props["max_depth"] = int(it.max_depth)
        props["rr_depth"] = int(it.rr_depth)
        if name in PROJECTIVE:
            props.update({p: getattr(it, p) for p in _PROJECTIVE_PROPS
                          if getattr(it, p, None) is not None})
    else:
        name = _NATIVE.get(shown, "")
        for prop in ("max_depth", "rr_depth"):
            m = re.search(rf"{prop}\s*=\s*(-?\d+)", text)
            if m:
                props[prop] = int(m.group(1))
    if "max_depth" in props:
        depth = props["max_depth"]
        props["max_depth"] = UNBOUNDED if depth < 0 or depth >= 2**31 - 1 else depth
    return Own(name, props, shown)


@dataclass
class Chosen:
    """The integrator a job renders with (``name`` and its properties but the depth), why, its
    depth (the scene's own until the depth choice cuts it) with where that came from, and
    ``changed``: what of the scene's integrator was replaced or amended and why ("" when it
    renders as the scene says)."""

    name: str
    why: str
    max_depth: int
    depth_origin: str
    props: dict = field(default_factory=dict)
    changed: str = ""

    @property
    def has_depth(self) -> bool:
        return self.name != "direct_projective"

    def reason(self) -> str:
        if not self.has_depth:
            return f"{self.why}; the scene renders direct light only"
        shown = "unbounded" if self.max_depth < 0 else self.max_depth
        return f"{self.why}; max_depth {shown} ({self.depth_origin})"


def choose(scene: mi.Scene, selected: list[str]) -> Chosen:
    """The scene's integrator where it differentiates ``selected`` (media need prbvolpath,
    moving edges a projective one); else the cheapest that does, with its depth, rr_depth and
    hide_emitters, and ``changed`` saying what and why."""
    own = read(scene)
    if own.max_depth is not None:
        depth, origin = own.max_depth, "the scene's"
    elif own.name == "direct":
        depth, origin = 2, "the scene's direct light"
    else:
        depth, origin = DEFAULT_MAX_DEPTH, "default"
    geometry = [k for k in selected if k.endswith(_GEOMETRY)]
    kept = {k: v for k, v in own.props.items() if k != "max_depth"}
    carried = {k: v for k, v in kept.items() if k in ("rr_depth", "hide_emitters")}
    scenes = (f"the scene's {own.name or own.shown}" if own.name or own.shown
              else "a scene without an integrator (Mitsuba's path tracer)")

    def keep(why: str) -> Chosen:
        spp = ", ".join(f"{k} {kept[k]}" for k in ("sppc", "sppp", "sppi") if k in kept)
        return Chosen(own.name, f"{why}: the scene's {own.name} as it stands"
                      + (f" ({spp})" if spp else ""), depth, origin, kept)

    def replace(name: str, why: str, because: str) -> Chosen:
        kept_ = ", ".join(k for k in ("max_depth", "rr_depth", "hide_emitters")
                          if k in own.props) or "nothing"
        changed = f"integrator: {name} instead of {scenes}, {because}; carried over: {kept_}"
        return Chosen(name, f"{why}: {name} in place of {scenes}", depth, origin,
                      dict(carried), changed)

    if has_media(scene):
        why = "the scene has participating media"
        if own.name == "prbvolpath":
            return keep(why)
        return replace("prbvolpath", why, "which does not differentiate media (prbvolpath is "
                       "Mitsuba's one integrator that does)")
    if geometry:
        why = f"{geometry[0]} moves visibility edges, which needs projective sampling"
        if own.name in PROJECTIVE:
            return keep(why)
        # Projective sampling of indirect visibility is costly (prb_projective: ~30x prb on a
        # CPU); a scene that only needs direct light gets the much cheaper direct_projective.
        direct = own.name == "direct" or 0 < depth <= 2
        return replace("direct_projective" if direct else "prb_projective", why,
                       "which does not sample the silhouettes a moving edge needs")
    why = "surface materials only"
    if own.name in ("prb", "prb_basic", "prbvolpath"):
        return keep(why)
    if own.name in PROJECTIVE:
        because = ("whose silhouette sampling serves parameters that move edges, and none is "
                   "selected: prb renders the same image and gradient at a fraction of the cost")
    else:
        because = "which is not differentiable (prb is its differentiable counterpart)"
    return replace("prb", why, because)


def make(chosen: Chosen, max_depth: int | None = None,
         shelf: dict[str, object] | None = None) -> mi.Integrator:
    """The integrator as chosen, at ``max_depth`` (default: the chosen depth); the one on
    ``shelf`` (a kept scene's) when it was made with the same properties, else a new one put
    there: a frozen recording replays only with the integrator it was made with."""
    props = {"type": chosen.name, **chosen.props}
    if chosen.has_depth:
        props["max_depth"] = chosen.max_depth if max_depth is None else max_depth
    key = repr(sorted(props.items()))
    made = (shelf or {}).get("integrator")
    if made is not None and made[0] == key:
        return made[1]
    integrator = mi.load_dict(props)
    if shelf is not None:
        shelf["integrator"] = (key, integrator)
    return integrator


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
