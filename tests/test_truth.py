"""The figures a job records against ground truth: PSNR and per-channel correlation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from matoptd.truth import correlation, parameter_error, psnr


def test_psnr_is_against_the_truths_peak():
    truth = np.array([0.2, 0.8, 0.4])
    assert psnr(0.008, truth) == pytest.approx(40.0)  # 20 log10(0.8 / 0.008)
    assert psnr(0.1, np.zeros(3)) == pytest.approx(20.0)  # peak 1 for an all-zero truth
    assert psnr(0.0, truth) == math.inf


def test_correlation_is_per_channel_and_ignores_scale_and_offset():
    rng = np.random.default_rng(1)
    truth = rng.random((8, 8, 3))
    estimate = truth.copy()
    estimate[..., 0] = 2 * truth[..., 0] + 0.5   # same pattern, other scale: r = 1
    estimate[..., 1] = rng.random((8, 8))         # no pattern: r near 0
    estimate[..., 2] = 0.3                        # constant: nothing to compare
    r = correlation(estimate.ravel(), truth.ravel(), 3)
    assert r[0] == pytest.approx(1.0)
    assert abs(r[1]) < 0.3
    assert math.isnan(r[2])


def test_parameter_error_adds_correlation_only_for_channelled_parameters():
    truth = np.array([0.5, 0.25, 0.75, 1.0])
    value = truth + np.array([0.1, -0.1, 0.1, -0.1])
    e = parameter_error(value, truth)
    assert (e.max_abs, e.rmse) == pytest.approx((0.1, 0.1))
    assert e.psnr == pytest.approx(20.0)  # peak 1.0, rmse 0.1
    assert e.correlation == []
    assert len(parameter_error(value, truth, channels=1).correlation) == 1
