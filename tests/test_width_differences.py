"""The microfacet width beside a dielectric's eta by central differences of the loss in its step
variable (width_differences, a candidate off unless named): which widths it takes, the slope it
gives Adam against the loss's own derivative, and where it leaves back-propagation alone. Pure
logic on a stand-in for the job's renders; a job with it on is in tests/test_choices.py."""

from __future__ import annotations

import contextlib
import types

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from matoptd.engine.choices.width_differences import STEP, WIDE, WidthDifferences
from matoptd.engine.diagnosis import Kept

from test_choices import ALPHA, ROUGHNESS, _interface, _principled, _set_up

GAIN, TRUTH = 10.0, 0.01  # the stand-in's image: GAIN * alpha, one pixel; its reference


class _Job:
    """What the choice reads of a job: a width at ``value``, stepped as log v (``logged``) or
    as v, and a one-pixel sensor that renders GAIN * the width, against GAIN * TRUTH."""

    def __init__(self, value: float, logged: bool = True, lo: float = 0.0) -> None:
        mi.set_variant("llvm_ad_rgb")
        self.v, self.logged, self.lo = value, logged, lo
        self.spp, self.held, self.sensors = 16, set(), [(0, 0)]
        self.images = {0: [mi.Float(GAIN * value)]}
        self.shown = value

    def value(self, key):
        return np.array([self.v])

    def encoded(self, key, value):
        return np.log(value) if self.logged else np.asarray(value, float)

    def latent(self, key):
        return self.encoded(key, self.value(key))

    def kept(self, key):
        return Kept(self.lo, 1.0, log=self.logged)

    @contextlib.contextmanager
    def holding(self, values):
        self.shown = float(values[ALPHA][0])
        yield
        self.shown = self.v

    def sensor_images(self, n, sensor, draw, spp):
        return [mi.Float(GAIN * self.shown)]

    def image_loss(self, images, sensor):
        return dr.square(images[0] - GAIN * TRUTH)


def _choice(job: _Job) -> WidthDifferences:
    settings, records = _interface(width_differences="on")
    records[ALPHA].lo = job.lo
    choice = WidthDifferences(settings)
    _set_up([choice], settings, records)
    return choice


@pytest.mark.parametrize("logged", [True, False])
def test_the_slope_is_the_losss_derivative_in_the_step_variable(logged):
    """L = (GAIN v - GAIN TRUTH)^2: dL/du = 2 GAIN (GAIN v - GAIN TRUTH) dv/du, dv/du = v in
    log space, 1 stepped as v: the difference's scale follows the step variable."""
    job = _Job(0.05, logged)
    slope = float(_choice(job).on_gradient(job)[ALPHA][0])
    dv_du = job.v if logged else 1.0
    assert slope == pytest.approx(2 * GAIN * GAIN * (job.v - TRUTH) * dv_du, rel=0.01)


def test_at_the_range_the_sides_are_clipped_and_the_slope_keeps_its_scale():
    # stepped as v from 0.05 with h 0.1 and the range from 0: the lower side is clipped to 0
    job = _Job(0.05, logged=False, lo=0.0)
    assert job.v - STEP < job.lo
    slope = float(_choice(job).on_gradient(job)[ALPHA][0])
    assert slope == pytest.approx(2 * GAIN * GAIN * (job.v - TRUTH), rel=0.01)


def test_a_rough_or_held_width_keeps_its_back_propagated_gradient():
    assert _choice(job := _Job(WIDE * 1.01)).on_gradient(job) == {}
    job = _Job(0.05)
    choice = _choice(job)
    job.held.add(ALPHA)
    assert choice.on_gradient(job) == {}


def test_it_takes_the_width_beside_an_eta_only_when_named():
    settings, records = _interface(width_differences="on")
    choice = WidthDifferences(settings)
    _set_up([choice], settings, records)
    assert choice.on and choice.keys == [ALPHA]
    assert "central differences" in choice.why and ALPHA in choice.notes()[0]
    settings, records = _principled(width_differences="on")
    choice = WidthDifferences(settings)
    _set_up([choice], settings, records)
    assert choice.keys == [ROUGHNESS]
    # Off by default, saying what stands instead; no eta beside the width: nothing to take.
    settings, records = _interface()
    choice = WidthDifferences(settings)
    _set_up([choice], settings, records)
    assert not choice.on and choice.applies and "back-propagation alone" in choice.why
    settings, records = _principled(eta=False, width_differences="on")
    choice = WidthDifferences(settings)
    _set_up([choice], settings, records)
    assert not choice.applies and choice.keys == []

