"""When a dielectric's eta gets its gradient by central differences instead of prb's AD: only
near the specular limit, where prb's detached refraction sampling leaves the AD gradient with
a random sign; and the difference kept once eta settles. Pure logic on the parameter keys and
values and on a stand-in for the job's renders; the jobs that rely on it are in
tests/test_thesis_tables.py."""

from __future__ import annotations

import contextlib

import mitsuba as mi
import numpy as np
import pytest

from matoptd.engine.choices import eta_differences
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


class _Sides:
    """What ``_difference`` reads of a job's context: eta set to a side, and that side's
    render, here 10 eta + the draw's noise: h D = (I(eta + h) - I(eta - h)) / 2 = 10 h + the
    noises' half difference."""

    def __init__(self, noises):
        self.noises, self.eta, self.sensors = iter(noises), 0.0, [(0, 0)]

    @contextlib.contextmanager
    def holding(self, values):
        self.eta = float(values["eta"][0])
        yield

    def sensor_images(self, n, sensor, draw, spp):
        return [mi.TensorXf(np.full((1, 1, 1), 10 * self.eta + next(self.noises), np.float32))]


def _kept(choice) -> float:
    return float(np.array(choice.kept["eta"][0][0]).ravel()[0])


def test_once_eta_settles_its_difference_is_the_mean_of_the_last_kept_while_it_moves_the_newest():
    """D's noise is most of the slope's: once eta has settled, D is the mean of the last KEPT
    differences; while eta moves, J moves with it and the newest difference stands alone."""
    mi.set_variant("llvm_ad_rgb")
    step = eta_differences.STEP
    choice = eta_differences.EtaDifferences.__new__(eta_differences.EtaDifferences)
    choice.kept, choice.taken = {"eta": {}}, {"eta": {}}
    # noise -e on the lower side, +e on the upper: h D = 10 h + e
    errors = [0.3, -0.1, 0.2, -0.4]
    sides = _Sides([x for e in errors for x in (-e, e)])
    choice._difference(sides, "eta", 1.5 - step, 1.5 + step, 2, settled=False)
    assert _kept(choice) == pytest.approx(10 * step + 0.3, abs=1e-5)
    choice._difference(sides, "eta", 1.5 - step, 1.5 + step, 2, settled=False)
    assert _kept(choice) == pytest.approx(10 * step - 0.1, abs=1e-5)  # the newest alone
    for _ in range(2):
        choice._difference(sides, "eta", 1.5 - step, 1.5 + step, 2, settled=True)
    # settled: the mean of the differences since, the first of them the newest before it
    assert _kept(choice) == pytest.approx(10 * step + (-0.1 + 0.2 - 0.4) / 3, abs=1e-5)
    many = _Sides([x for _ in range(3 * eta_differences.KEPT) for x in (0.0, 0.0)])
    for _ in range(3 * eta_differences.KEPT):
        choice._difference(many, "eta", 1.5 - step, 1.5 + step, 2, settled=True)
    # the old noises fade: of the last KEPT only (an exponential mean that long)
    assert abs(_kept(choice) - 10 * step) < 0.3 * (1 - 1 / eta_differences.KEPT) ** (
        2 * eta_differences.KEPT)
