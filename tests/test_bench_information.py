"""bench/information's estimate of what images decide, on a linear model whose answer is known:
I = J theta + e with Gaussian pixel noise of a known sigma, J from two noisy estimates."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import information  # noqa: E402


def test_the_fits_spread_is_sigma_squared_times_the_inverse_of_jtj_even_from_noisy_j():
    rng = np.random.default_rng(0)
    pixels, sigma = 4000, 0.05
    j = rng.standard_normal((pixels, 3)) * [1.0, 0.3, 0.1]
    j[:, 2] += 0.5 * j[:, 0]  # correlated columns: the sandwich must not read them apart
    # Each estimate of J carries noise as large as its weakest column's signal.
    ja, jb = (j + 0.1 * rng.standard_normal(j.shape) for _ in range(2))
    noise = sigma * rng.standard_normal((400, pixels))
    blocks = np.arange(pixels) // 40  # independent pixels
    cov = information.spread(ja, jb, information.meat(ja, jb, noise, blocks))
    truth = sigma ** 2 * np.linalg.inv(j.T @ j)
    assert np.allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(truth)), rtol=0.1), (cov, truth)
    # J's own noise, multiplied with itself, would have shrunk the weakest column's spread.
    naive = sigma ** 2 * np.linalg.inv(ja.T @ ja)
    assert np.sqrt(naive[2, 2]) < 0.8 * np.sqrt(truth[2, 2])


def test_noise_correlated_within_a_block_counts_as_the_blocks_own():
    """Neighbouring pixels share their noise (a reconstruction filter): the fit's spread is
    the blocks', which a sum over single pixels would miss by the square root of their size."""
    rng = np.random.default_rng(1)
    film, sigma = (32, 16), 0.05
    blocks = information.image_blocks(film, 4)
    assert blocks.shape == (32 * 16 * 3,) and len(np.unique(blocks)) == 32
    j = rng.standard_normal((blocks.size, 1)) ** 2 + 0.5  # one positive column
    # the noise: one draw per 4x4 block, shared by its 48 pixel-channels
    noise = sigma * rng.standard_normal((400, 32))[:, blocks]
    cov = information.spread(j, j, information.meat(j, j, noise, blocks))
    per_block = np.array([j[blocks == b, 0].sum() for b in range(32)])
    truth = sigma ** 2 * (per_block ** 2).sum() / (j[:, 0] @ j[:, 0]) ** 2
    assert np.sqrt(cov[0, 0]) == pytest.approx(np.sqrt(truth), rel=0.1)
    alone = information.spread(j, j, information.meat(j, j, noise, np.arange(blocks.size)))
    assert np.sqrt(alone[0, 0]) < 0.3 * np.sqrt(truth)


def test_the_median_worst_error_of_independent_fits_is_the_median_of_their_largest():
    """Two parameters each with a 1% spread: the worst of two |N(0, 1%)| has its median at
    1.0518% (P(max < x) = (2 Phi(x) - 1)^2 = 1/2); a colour counts as the rms over its channels."""
    cov = np.diag([1e-4, 1e-4])
    worst = information.worst_median(cov, np.ones(2), [np.array([0]), np.array([1])])
    assert abs(worst - 0.010518) < 0.0003
    colour = information.worst_median(np.diag([1e-4] * 3), np.ones(3), [np.array([0, 1, 2])])
    assert abs(colour - 0.01 * np.sqrt(2.366 / 3)) < 0.0003  # chi-square(3)'s median / 3


def test_a_gradient_with_only_the_images_noise_is_one_renders_worth_and_a_noisier_one_more():
    """g = 2 J^T e (an efficient gradient) carries one render's noise; each path's derivative
    noise on top (J's rows drawn anew per gradient) adds its variance over the signal's."""
    rng = np.random.default_rng(1)
    pixels, sigma, n = 2000, 0.05, 3000
    j = rng.standard_normal((pixels, 2)) * [1.0, 0.2]
    e = sigma * rng.standard_normal((n, pixels))
    images = information.meat(j, j, e[:400], np.arange(pixels))  # independent pixels
    assert np.allclose(information.back_propagated(2 * e @ j, images), 1.0, rtol=0.15)
    noisy = np.stack([2 * row @ (j + 0.5 * rng.standard_normal(j.shape)) for row in e])
    # a column's variance grows by the derivative noise's over its signal's: 1 + 0.25 / J_k^2
    assert np.allclose(information.back_propagated(noisy, images),
                       1 + 0.25 / np.array([1.0, 0.04]), rtol=0.15)


def test_a_cut_that_darkens_the_images_along_a_column_biases_the_fit_by_that_columns_share():
    """Rendering at a cut depth against references at the file's own: the fit moves to where
    the cut images match the references, theta + d with J d = -b, from noisy estimates of J."""
    rng = np.random.default_rng(2)
    pixels = 3000
    j = rng.standard_normal((pixels, 3)) * [1.0, 0.5, 0.2]
    ja, jb = (j + 0.1 * rng.standard_normal(j.shape) for _ in range(2))
    darkening = j @ np.array([-0.01, 0.0, 0.002])  # the cut's images: I_cut = I_whole + b

    class Images:  # renders at the truth, the same samples at either depth
        def __init__(self, b):
            self.table, self.b = type("T", (), {"truth": {}})(), b

        def render(self, truth, spp, seed):
            return np.full(pixels, 0.3) + self.b

    bias = information.cut_bias(Images(darkening), Images(0.0), ja, jb)
    assert np.allclose(bias, [0.01, 0.0, -0.002], atol=5e-4), bias


def test_a_spread_whose_variance_came_out_negative_reads_not_settled_not_zero():
    assert information._pct(float("nan")) == "not settled"
    assert information._pct(0.0123) == "1.23%"
    assert information._ad(float("nan"), 2.0) == "not settled"
