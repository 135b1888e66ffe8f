"""Scaling a film's reconstruction filter with JobSpec.film_height (pure rule, no Mitsuba)."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest

from matoptd.engine.film_filter import Scaled, rewrite, scale


def test_gaussian_and_tent_scale_with_the_film_height():
    # Mitsuba's default gaussian: stddev 0.5, radius 2; at half the height, half the pixels.
    assert scale("gaussian", 2.0, 0.5) == Scaled("gaussian", "stddev", 0.5, 0.25)
    assert scale("tent", 1.5, 2.0) == Scaled("tent", "radius", 1.5, 3.0)
    for fixed in ("box", "mitchell", "catmullrom", "lanczos"):
        assert scale(fixed, 2.0, 0.5) is None


XML = b"""<scene version="3.0.0">
  <sensor type="perspective" id="a"><film type="hdrfilm"><rfilter type="gaussian">
    <float name="stddev" value="$sd"/></rfilter></film></sensor>
  <sensor type="perspective" id="b"><film type="hdrfilm"/></sensor>
</scene>"""


def test_rewrite_replaces_or_adds_each_sensors_filter():
    out, missing = rewrite(XML, {"a": Scaled("gaussian", "stddev", 0.75, 0.375),
                                 "b": Scaled("gaussian", "stddev", 0.5, 1.0),
                                 "elsewhere": Scaled("tent", "radius", 1, 2)})
    assert missing == ["elsewhere"]
    root = ET.fromstring(out)
    for sid, value in (("a", 0.375), ("b", 1.0)):
        filters = root.findall(f"./sensor[@id='{sid}']/film/rfilter")
        assert len(filters) == 1 and filters[0].get("type") == "gaussian"
        assert float(filters[0].find("float[@name='stddev']").get("value")) == pytest.approx(value)
