"""Scaling a film's reconstruction filter with the film: pure logic, no Mitsuba.

A filter's size is in pixels. A 3-pixel Gaussian on a film rendered at half the height of the
scene's own covers twice the share of the image, so the renders come out blurrier than the
references made at the scene's size, and the loss has a floor no parameter can reach. When
JobSpec.film_height changes a film's height, the filter is scaled by the same ratio where
Mitsuba lets its size be set (gaussian: stddev, radius 4 stddev; tent: radius); the others
(box is always one pixel; mitchell, catmullrom, lanczos have fixed radii) are left alone and
the job's notes say so.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

# Mitsuba's class name of a filter (as its str() starts) -> the XML plugin type.
PLUGINS = {"GaussianFilter": "gaussian", "TentFilter": "tent", "BoxFilter": "box",
           "MitchellNetravaliFilter": "mitchell", "CatmullRomFilter": "catmullrom",
           "LanczosSincFilter": "lanczos"}


@dataclass(frozen=True)
class Scaled:
    plugin: str    # "gaussian" or "tent"
    property: str  # the size Mitsuba reads: "stddev" or "radius"
    before: float  # pixels, on the scene's film
    after: float   # pixels, on the film rendered


def scale(plugin: str, radius: float, ratio: float) -> Scaled | None:
    """The filter's size on a film ``ratio`` times the scene's height; None for a filter whose
    size Mitsuba does not let be set. ``radius`` is Mitsuba's ``rfilter.radius()``."""
    if plugin == "gaussian":  # Mitsuba: radius = 4 stddev
        return Scaled("gaussian", "stddev", radius / 4, radius / 4 * ratio)
    if plugin == "tent":
        return Scaled("tent", "radius", radius, radius * ratio)
    return None


def rewrite(xml: bytes, sizes: dict[str, Scaled]) -> tuple[bytes, list[str]]:
    """The scene XML with the filter of each sensor named in ``sizes`` (by id) set to its new
    size; returns it and the ids of the sensors that could not be rewritten (their film is
    not written inside a top-level <sensor> of this file, e.g. an <include>d one)."""
    root = ET.fromstring(xml)
    missing = []
    for sensor_id, s in sizes.items():
        film = next((f for e in root if e.tag == "sensor" and e.get("id") == sensor_id
                     for f in e if f.tag == "film"), None)
        if film is None:
            missing.append(sensor_id)
            continue
        for old in [c for c in film if c.tag == "rfilter"]:
            film.remove(old)
        rfilter = ET.SubElement(film, "rfilter", type=s.plugin)
        ET.SubElement(rfilter, "float", name=s.property, value=repr(float(s.after)))
    return ET.tostring(root, encoding="utf-8", xml_declaration=True), missing
