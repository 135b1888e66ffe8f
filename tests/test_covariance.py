"""The covariance model behind the standard errors (engine/covariance.py) as pure logic on
synthetic Jacobians and noise: no renderer, no daemon."""

from __future__ import annotations

import numpy as np
import pytest

from matoptd.engine.covariance import (BETA_2, Dynamics, Linearized, adam_scatter, correlated,
                                       crossed, determined, estimate, gradient_noise, remaining,
                                       residual_noise)


def _dynamics(rates: np.ndarray, v_hat: np.ndarray, gradients: np.ndarray | None = None
              ) -> Dynamics:
    steps, p = rates.shape
    return Dynamics(rates, v_hat * (1 - BETA_2 ** steps), steps, np.ones(p, dtype=bool),
                    np.full((0, p), np.nan) if gradients is None else gradients)


def test_however_large_the_rate_the_scatter_is_at_most_the_fit_to_one_render():
    """Steps far too large for the curvature would, linearized, grow without bound; Adam's v,
    inflated by the overshoots, brings them back. The value then scatters as sigma^2
    (J^T J)^-1 with one render's noise (Q / H^2 here), the textbook estimate, and no more."""
    h, q = np.array([[4.0]]), np.array([[9.0]])
    for rate in (10.0, 1000.0):
        p = adam_scatter(h, q, _dynamics(np.full((400, 1), rate), np.array([9.0])))
        assert 0.6 * 9.0 / 16.0 < p[0, 0] <= 1.1 * 9.0 / 16.0, rate


def test_a_long_job_at_a_small_rate_averages_many_renders():
    """At a constant small effective rate eta = lr / sqrt(v), the value settles to a
    stationary scatter of about eta Q / (2 H), far below one render's Q / H^2: the model
    follows the schedule, not a fixed formula."""
    h, q = np.array([[4.0]]), np.array([[9.0]])
    rate = 0.03
    eta = rate / 3.0
    p = adam_scatter(h, q, _dynamics(np.full((600, 1), rate), np.array([9.0])))
    assert p[0, 0] == pytest.approx(eta * 9.0 / (2 * 4.0), rel=0.15)
    assert p[0, 0] < 0.05 * 9.0 / 16.0


def test_a_start_far_away_shrinks_the_late_steps():
    """Adam's v holds the large gradients of a far start: with v measured ten times what the
    noise alone gives, every step is ~3x shorter and the scatter smaller."""
    h, q = np.array([[4.0]]), np.array([[9.0]])
    rates = np.full((100, 1), 0.3)
    near = adam_scatter(h, q, _dynamics(rates, np.array([9.0])))
    far = adam_scatter(h, q, _dynamics(rates, np.array([90.0])))
    assert far[0, 0] < 0.5 * near[0, 0]


def test_the_scatter_follows_the_jobs_momentum():
    """medium_damping runs Adam at beta_1 0.5: the model carries the job's beta_1 and agrees
    with Adam itself, simulated on a quadratic with noisy gradients over many chains, where
    Dr.Jit's 0.9 in its place would call the scatter 15% narrower than it is."""
    h, q, steps, rate = 4.0, 9.0, 300, 1.0
    rng = np.random.default_rng(0)
    d, m, v = np.zeros(20000), np.zeros(20000), np.zeros(20000)
    for t in range(1, steps + 1):
        g = h * d + rng.normal(0.0, 3.0, d.shape)
        m, v = 0.5 * m + 0.5 * g, BETA_2 * v + (1 - BETA_2) * g * g
        d = d - rate * np.sqrt(1 - BETA_2 ** t) / (1 - 0.5 ** t) * m / (np.sqrt(v) + 1e-8)

    def model(beta_1: float) -> float:
        v_hat = np.array([np.mean(v)]) / (1 - BETA_2 ** steps)
        dynamics = _dynamics(np.full((steps, 1), rate), v_hat)
        dynamics.beta_1 = beta_1
        return adam_scatter(np.array([[h]]), np.array([[q]]), dynamics)[0, 0]

    assert model(0.5) == pytest.approx(np.var(d), rel=0.05)
    assert model(0.9) < 0.9 * np.var(d)


def test_crossing_two_estimates_keeps_their_noise_out_of_j_transpose_j():
    rng = np.random.default_rng(1)
    j = rng.normal(size=(400, 2))
    truth = j.T @ j
    crossed_mean = np.zeros((2, 2))
    naive_mean = np.zeros((2, 2))
    for _ in range(50):
        a, b = (j + 2.0 * rng.normal(size=j.shape) for _ in range(2))
        crossed_mean += crossed(a, b, np.ones(400))[0] / 50
        naive_mean += a.T @ a / 50
    assert np.diag(crossed_mean) == pytest.approx(np.diag(truth), rel=0.05)
    assert np.all(np.diag(naive_mean) > 4 * np.diag(truth))  # noise variance 4 per row


def test_components_the_images_cannot_tell_apart_are_not_determined():
    """Two columns of J that are equal (a light and a gain scaling the same image) are not
    determined; a third, independent one is, with its own finite inverse."""
    rng = np.random.default_rng(2)
    shared, other = rng.normal(size=400), rng.normal(size=400)
    j = np.stack([shared, shared, other], axis=1)
    a, b = (j + 0.05 * rng.normal(size=j.shape) for _ in range(2))
    h, spread = crossed(a, b, np.ones(400))
    ok, inverse, _, groups = determined(h, spread)
    assert list(ok) == [False, False, True] and groups == [[0, 1]]
    assert inverse[2, 2] == pytest.approx(1 / (other @ other), rel=0.05)
    # A component too noisy to tell, whose J runs along a determined one's (a light and a
    # gain), takes that one with it: held at its value it would make the other look decided.
    h = np.array([[0.1, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    spread = np.array([[0.5, 0.01, 0.01], [0.01, 0.01, 0.01], [0.01, 0.01, 0.01]])
    ok, _, noisy, groups = determined(h, spread)
    assert list(ok) == [False, False, True] and groups == [[0, 1]] and not noisy.any()
    # A component the render does not depend on at all is not determined either.
    zero = np.stack([other, np.zeros(400)], axis=1)
    ok, _, _, _ = determined(zero.T @ zero, np.zeros((2, 2)))
    assert list(ok) == [True, False]


def test_the_estimate_zeroes_what_is_not_determined_and_never_gives_nan():
    h = np.array([[1.0, 1.0], [1.0, 1.0]])
    fit = Linearized(h, np.eye(2), np.eye(2) * 0.1, np.zeros((2, 2)))
    result = estimate(fit, _dynamics(np.full((20, 2), 0.1), np.ones(2)))
    assert not result.determined.any()
    assert np.all(np.isfinite(result.covariance))


def test_recorded_gradients_scale_the_modelled_noise():
    """The gradients the job saw vary twice as much as J and the render noise say (the
    derivative estimate's own noise): Q is scaled up to them, keeping its correlations;
    a component without records takes the others' scale."""
    rng = np.random.default_rng(3)
    model = np.array([[1.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 4.0]])
    seen = rng.normal(size=(4000, 2)) * np.sqrt(2.0)
    gradients = np.concatenate([seen, np.full((4000, 1), np.nan)], axis=1)
    q = gradient_noise(model, np.zeros((3, 3)), np.zeros((3, 3)), gradients)
    assert np.diag(q) == pytest.approx([2.0, 2.0, 8.0], rel=0.1)
    assert q[0, 1] == pytest.approx(1.0, rel=0.1)
    # never below the model
    quiet = gradient_noise(model, np.zeros((3, 3)), np.zeros((3, 3)), 0.1 * gradients)
    assert np.diag(quiet) == pytest.approx(np.diag(model))


def test_a_job_still_on_its_way_is_a_newton_step_from_the_optimum():
    """Gradients that keep one sign (mean 0.4 with H = 2) say the value is about 0.2 from
    where the images point; gradients around 0 say nothing."""
    rng = np.random.default_rng(4)
    inverse = np.array([[0.5]])
    moving = 0.4 + 0.05 * rng.normal(size=(30, 1))
    assert remaining(inverse, moving)[0][0] == pytest.approx(0.2, rel=0.05)
    settled = 0.05 * rng.normal(size=(30, 1))
    assert abs(remaining(inverse, settled)[0][0]) < 0.01
    assert remaining(inverse, moving[:5]) == (0, 0)  # too few to say


def test_a_settled_job_gets_no_distance_to_go_and_a_moving_one_does():
    """A settled job's mean gradient is where its last steps wandered plus noise, which the
    scatter already counts: no bias is added for it. One whose gradients keep a sign far
    beyond that gets the Newton step's square on top."""
    rng = np.random.default_rng(5)
    fit = Linearized(np.array([[2.0]]), np.array([[1.0]]), np.array([[0.0]]),
                     np.zeros((1, 1)))
    rates = np.full((60, 1), 0.01)
    added = [(e.covariance - e.noise)[0, 0] / e.noise[0, 0] for e in (
        estimate(fit, _dynamics(rates, np.ones(1), rng.normal(size=(17, 1))))
        for _ in range(50))]
    assert np.mean(added) < 0.1  # counted twice, it would be about 1
    moving = estimate(fit, _dynamics(rates, np.ones(1), 4.0 + rng.normal(size=(17, 1))))
    assert moving.covariance[0, 0] > moving.noise[0, 0] + 2.0  # (H^-1 g)^2 = (4 / 2)^2


def test_a_rendered_reference_takes_its_noise_from_every_pixel_a_misfit_from_its_own():
    """A reference rendered with 8x the job's samples: its noise is one eighth of the render
    noise, which the residual of the few pixels J weights (here 20 of 4000) estimates to
    within +-100% or worse, but every pixel together far better. A misfit where J is
    large (a highlight the scene does not model) keeps the per-pixel estimate."""
    rng = np.random.default_rng(6)
    rows = 4000
    j = np.zeros((rows, 1))
    j[:20, 0] = 1.0
    noise = rng.uniform(0.5, 1.5, rows)
    truth = crossed(j, j, noise / 8)[0][0, 0]
    pooled, pixel = [], []
    for _ in range(200):
        a, b, r = (rng.normal(size=rows) * np.sqrt(s) for s in (noise, noise, noise / 8))
        residual = (a - r) * (b - r)
        pooled.append(residual_noise(j, j, (a - b) / np.sqrt(2), a - r, b - r, np.ones(rows),
                                     1)[0, 0])
        pixel.append(crossed(j, j, residual)[0][0, 0])
    assert np.mean(pooled) == pytest.approx(truth, rel=0.15)
    assert np.std(pooled) < 0.3 * np.std(pixel)
    misfit = np.zeros(rows)
    misfit[:20] = 3.0
    a, b = (rng.normal(size=rows) * np.sqrt(noise) for _ in range(2))
    residual = (a - misfit) * (b - misfit)
    kept = residual_noise(j, j, (a - b) / np.sqrt(2), a - misfit, b - misfit, np.ones(rows),
                          1)[0, 0]
    assert kept == pytest.approx(crossed(j, j, residual)[0][0, 0])
    assert kept > 20 * 9.0 * 0.5


def test_noise_shared_by_a_pixels_channels_counts_for_a_scalar_that_moves_all_three():
    """One path carries a sample's three channels, so a white highlight's noise moves them
    together. A scalar (a roughness) moves all three: the variance of its J-weighted sum of a
    reference is the channels' covariance summed, up to 3x their variances' sum, and the
    reference's term must say so; a colour's channel (its J in one channel) is unchanged."""
    rng = np.random.default_rng(7)
    pixels, channels = 300, 3
    j = np.zeros((pixels * channels, 2))
    j[:, 0] = rng.uniform(0.5, 1.0, pixels).repeat(channels)  # a scalar: every channel
    j[0::channels, 1] = rng.uniform(0.5, 1.0, pixels)          # a colour's red channel
    sigma = rng.uniform(0.5, 1.5, pixels)

    def draw(scale=1.0):  # the same noise in a pixel's three channels
        return (rng.normal(size=pixels) * sigma * scale).repeat(channels)

    shifts = []
    estimates = []
    for _ in range(300):
        a, b, r = draw(), draw(), draw(np.sqrt(1 / 8))
        shifts.append(j.T @ r)  # what the reference moves the fit by, before H^-1
        estimates.append(residual_noise(j, j, (a - b) / np.sqrt(2), a - r, b - r,
                                        np.ones(len(a)), channels))
    truth = np.cov(np.array(shifts).T)
    mean = np.mean(estimates, axis=0)
    assert mean[0, 0] == pytest.approx(truth[0, 0], rel=0.2)
    assert mean[1, 1] == pytest.approx(truth[1, 1], rel=0.2)
    per_row = np.sum(j[:, 0] ** 2 * (sigma ** 2 / 8).repeat(channels))
    assert truth[0, 0] > 2.5 * per_row  # what the channels taken apart would have said


def test_strongly_correlated_pairs_are_named_strongest_first():
    cov = np.array([[1.0, 0.9, 0.0, -0.95],
                    [0.9, 1.0, 0.0, -0.7],
                    [0.0, 0.0, 1.0, 0.0],
                    [-0.95, -0.7, 0.0, 1.0]])
    pairs = correlated(cov, np.ones(4, dtype=bool), ["albedo", "base", "eta", "sigma_t"])
    assert [(a, b) for a, b, _ in pairs] == [("albedo", "sigma_t"), ("albedo", "base")]
    assert pairs[0][2] == pytest.approx(-0.95)
    assert correlated(cov, np.array([False, True, True, True]), list("abcd")) == []
