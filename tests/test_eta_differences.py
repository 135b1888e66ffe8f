"""When a dielectric's eta gets its gradient by central differences instead of prb's AD: only
near the specular limit, where prb's detached refraction sampling leaves the AD gradient with
a random sign. Pure logic on the parameter keys and values; the jobs that rely on it are in
tests/test_thesis_tables.py."""

from __future__ import annotations

import numpy as np
import pytest

from matoptd.engine.parameters import microfacet_alpha, microfacet_widths, near_specular
from matoptd.settings import SPECULAR_ALPHA, Differences, differences

PRINCIPLED = ["obj.bsdf.base_color.value", "obj.bsdf.roughness.value", "obj.bsdf.eta",
              "obj.bsdf.spec_trans.value"]


def test_the_width_beside_each_kind_of_dielectric_is_found():
    assert microfacet_widths("obj.bsdf.eta", PRINCIPLED) == ["obj.bsdf.roughness.value"]
    assert microfacet_widths("glass.bsdf.eta", ["glass.bsdf.alpha.value", "glass.bsdf.eta"]
                             ) == ["glass.bsdf.alpha.value"]
    anisotropic = ["g.bsdf.alpha_u.value", "g.bsdf.alpha_v.value", "g.bsdf.eta"]
    assert microfacet_widths("g.bsdf.eta", anisotropic) == anisotropic[:2]
    # A smooth dielectric has none; another object's width is not this one's.
    assert microfacet_widths("smooth.bsdf.eta", ["smooth.bsdf.eta"] + PRINCIPLED) == []


def test_alpha_as_the_surface_shows_it():
    # principled: alpha = max(0.001, roughness^2); a rough dielectric's alpha as it is
    assert microfacet_alpha("obj.bsdf.roughness.value", np.array([0.1])) == pytest.approx(0.01)
    assert microfacet_alpha("obj.bsdf.roughness.value", np.array([0.01])) == 0.001
    assert microfacet_alpha("glass.bsdf.alpha.value", np.array([0.3])) == pytest.approx(0.3)
    assert microfacet_alpha("glass.bsdf.alpha.data", np.array([0.0, 0.02])) == pytest.approx(
        0.01)  # a textured width by its mean


def test_differences_only_while_the_surface_is_near_specular():
    widths = {"obj.bsdf.roughness.value": np.array([0.3])}  # the scene's value
    assert not near_specular(widths, {}, SPECULAR_ALPHA)  # alpha 0.09: prb's own gradient
    # An optimized roughness is read at the current iteration: the switch follows it down.
    assert near_specular(widths, {"obj.bsdf.roughness.value": np.array([0.1])}, SPECULAR_ALPHA)
    assert not near_specular(widths, {"obj.bsdf.roughness.value": np.array([0.2])},
                             SPECULAR_ALPHA)
    # ... and a job's wider threshold (eta_differences=quarter:0.05) keeps alpha 0.04 in.
    assert near_specular(widths, {"obj.bsdf.roughness.value": np.array([0.2])}, 0.05)
    assert near_specular({}, {}, SPECULAR_ALPHA)  # a smooth dielectric: always
    # Anisotropic: only when both directions are narrow.
    both = {"g.bsdf.alpha_u.value": np.array([0.01]), "g.bsdf.alpha_v.value": np.array([0.3])}
    assert not near_specular(both, {}, SPECULAR_ALPHA)
    assert near_specular(both, {"g.bsdf.alpha_v.value": np.array([SPECULAR_ALPHA / 2])},
                         SPECULAR_ALPHA)


@pytest.mark.parametrize("value, how", [
    ("on", Differences(4, SPECULAR_ALPHA)), ("quarter", Differences(4, SPECULAR_ALPHA)),
    ("full", Differences(1, SPECULAR_ALPHA)), ("on:0.05", Differences(4, 0.05)),
    ("full:0.1", Differences(1, 0.1))])
def test_the_value_sets_the_sides_spp_and_the_width_below_which_they_apply(value, how):
    assert differences(value) == how


@pytest.mark.parametrize("value", ["half", "quarter:", "quarter:wide", "full:0", "on:1.5",
                                   "quarter:nan"])
def test_a_value_outside_the_grammar_is_refused_saying_what_it_may_be(value):
    with pytest.raises(ValueError, match=f"cannot be '{value}': give on, off, quarter or "
                                         r"full, optionally with :ALPHA"):
        differences(value)
