"""Loading a prepared scene and describing what a client needs to know about it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi

from ..engine_api import InvalidInput
from . import parameters


@dataclass
class Description:
    sensors: list[tuple[str, int, int]]  # (id, width, height)
    has_media: bool
    parameters: list[parameters.Info]


def load(loadable: Path, overrides: dict[str, str], display: str,
         keys: list[str] | None = None) -> mi.Scene:
    """Loads the XML; Mitsuba's own message (with the file and the offending tag) on failure.

    Mitsuba's parser can merge the meshes that share a BSDF into one anonymous mesh, which
    renders the same, faster (fewer shapes to trace and to dispatch over: 4% an iteration on
    the Cornell box), but the merged shapes lose their ids and with them their parameter
    keys. Without ``keys`` (listing every parameter) nothing is merged; with the keys a job
    optimizes, meshes are merged unless that would lose one of them.
    """
    try:
        if keys is not None:
            merged = mi.load_file(str(loadable), optimize=True, **overrides)
            if all(k in mi.traverse(merged) for k in keys):
                return merged
            del merged
        return mi.load_file(str(loadable), optimize=False, **overrides)
    except Exception as exc:  # Mitsuba raises RuntimeError/ValueError with the parser's text
        message = str(exc).replace(str(loadable), display).strip()
        raise InvalidInput(f"Mitsuba cannot load '{display}': {message}") from None


def has_media(scene: mi.Scene) -> bool:
    """Whether any shape bounds a medium or any sensor sits in one (then prbvolpath is needed)."""
    for shape in scene.shapes():
        if shape.interior_medium() is not None or shape.exterior_medium() is not None:
            return True
    return any(s.get_medium() is not None for s in scene.sensors())


def describe(scene: mi.Scene) -> Description:
    sensors = []
    for i, sensor in enumerate(scene.sensors()):
        size = sensor.film().crop_size()
        sensors.append((sensor.id() or f"sensor_{i}", int(size[0]), int(size[1])))
    return Description(sensors, has_media(scene), parameters.describe(mi.traverse(scene)))
