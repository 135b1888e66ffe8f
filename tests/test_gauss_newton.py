"""The gauss_newton choice: its damped step and trust region on a synthetic least-squares
problem (pure numpy), and a real small job in-process (a Cornell box's two wall colours from
far off) that it recovers, continued from a checkpoint along the same trajectory."""

from __future__ import annotations

import numpy as np
import pytest

from matoptd import settings as api
from matoptd.engine import trust_region

RED, GREEN = "red.reflectance.value", "green.reflectance.value"


def _problem(jacobian: np.ndarray, truth: np.ndarray):
    """L(u) = |J (u - truth)|^2: its exact H and gradient at u."""
    h = 2 * jacobian.T @ jacobian
    return h, (lambda u: h @ (u - truth))


def _solve(h, gradient, u, lo, hi, steps: int, spread=None):
    """Steps from u, each judged by the exact fall of L along it."""
    radius, scale = 2.0, np.full(len(u), 0.05)
    spread = np.zeros_like(h) if spread is None else spread
    for _ in range(steps):
        p = trust_region.step(h, gradient(u), spread, scale, radius, u, lo, hi)
        fell, noise = trust_region.fall(gradient(u), gradient(u + p.delta), np.zeros_like(h),
                                        np.zeros_like(h), p.delta)
        kept, radius = trust_region.judge(fell, noise + 1e-12, p.predicted, p.length, radius)
        u = u + p.delta if kept else u
    return u, p


def test_a_linear_least_squares_problem_is_solved_in_a_few_steps():
    rng = np.random.default_rng(1)
    jacobian = rng.normal(size=(50, 3)) * [1.0, 10.0, 0.1]  # curvatures 4 decades apart
    truth = np.array([0.3, 0.7, 0.5])
    h, gradient = _problem(jacobian, truth)
    wide = np.full(3, 10.0)
    u, p = _solve(h, gradient, np.zeros(3), -wide, wide, steps=6)
    np.testing.assert_allclose(u, truth, atol=1e-6)
    assert p.damped == []
    # The first step stays within its radius (in difference steps of 0.05).
    first = trust_region.step(h, gradient(np.zeros(3)), np.zeros_like(h), np.full(3, 0.05),
                              2.0, np.zeros(3), -wide, wide)
    assert first.length == pytest.approx(2.0, rel=1e-6) and first.predicted > 0


def test_a_bound_is_respected_and_the_others_reach_their_optimum_beside_it():
    jacobian = np.eye(2)
    truth = np.array([1.5, 0.4])  # the first beyond its bound at 1
    h, gradient = _problem(jacobian, truth)
    u, _ = _solve(h, gradient, np.array([0.5, 0.9]), np.zeros(2), np.ones(2), steps=8)
    np.testing.assert_allclose(u, [1.0, 0.4], atol=1e-9)


def test_a_singular_or_noise_swamped_direction_is_damped_not_stepped():
    # Two components that move the images alike: only their sum is determined.
    jacobian = np.array([[1.0, 1.0, 0.0], [2.0, 2.0, 0.0], [0.0, 0.0, 1.0]])
    truth = np.array([0.2, 0.2, 0.6])
    h, gradient = _problem(jacobian, truth)
    start = np.array([0.0, 0.4, 0.0])  # the sum already right: off only along the null space
    u, p = _solve(h, gradient, start, np.full(3, -5.0), np.full(3, 5.0), steps=6)
    assert p.damped in ([0], [1])
    np.testing.assert_allclose(u[:2], start[:2], atol=1e-9)  # not stepped along it
    assert u[2] == pytest.approx(0.6)
    # A direction whose curvature lies within its estimate's noise is damped: its curvature
    # taken at the noise's bound, it steps a thirtieth of the way the estimate says.
    noisy = np.diag([0.0, 0.0, 10.0 * h[2, 2]])
    off = np.zeros(3)
    p = trust_region.step(np.diag([h[0, 0], h[0, 0], h[2, 2]]), gradient(off), noisy,
                          np.full(3, 0.05), 100.0, off, np.full(3, -5.0), np.full(3, 5.0))
    assert p.damped == [2] and p.delta[2] == pytest.approx(0.6 / 30)
    np.testing.assert_allclose(p.delta[:2], -gradient(off)[:2] / h[0, 0])  # all the way


def test_a_rise_beyond_the_noise_is_undone_and_a_fall_grows_the_radius():
    assert trust_region.judge(-1.0, 0.1, 0.5, 2.0, 4.0) == (False, 0.5)
    assert trust_region.judge(1.0, 0.1, 0.5, 2.0, 4.0) == (True, 4.0)
    assert trust_region.judge(1.0, 0.1, 0.5, 3.0, 4.0) == (True, 6.0)
    # within the noise: kept; shrunk only where the model promised a fall it would show
    assert trust_region.judge(0.05, 0.1, 1.0, 2.0, 4.0) == (True, 1.0)
    assert trust_region.judge(0.05, 0.1, 0.1, 2.0, 4.0) == (True, 4.0)


def test_more_than_a_handful_of_components_or_a_texture_is_left_to_adam():
    import types
    from matoptd.engine.choices.gauss_newton import GaussNewton
    from matoptd.engine.records import ParamRecord
    settings = api.JobSettings(api.SceneInput("k", "s.xml", {}, {}, "s.xml"), [], [],
                               choices={"gauss_newton": "on"})
    ctx = types.SimpleNamespace(settings=settings)
    colour = (lambda key: ParamRecord(key, "rgb", 0.0, 1.0, 0.05, np.full(3, 0.5),
                                      np.full(3, 0.5)))
    texture = ParamRecord("t", "texture", 0.0, 1.0, 0.05, np.full(12, 0.5), np.full(12, 0.5))
    few = {"a": colour("a"), "b": colour("b"), "t": texture}
    assert GaussNewton(settings).select(ctx, few) == ["a", "b"]
    many = {k: colour(k) for k in "abcde"}
    choice = GaussNewton(settings)
    assert choice.select(ctx, many) == []
    assert choice.refused.startswith("15 scalar and colour components, more than 12")


mi = pytest.importorskip("mitsuba")


@pytest.fixture(scope="module")
def optimize():
    mi.set_variant("llvm_ad_rgb")
    from matoptd.engine import optimize
    return optimize


def _scene():
    scene = mi.cornell_box()
    scene["sensor"]["film"]["width"] = scene["sensor"]["film"]["height"] = 32
    scene["integrator"]["max_depth"] = 3
    return mi.load_dict(scene)


def _job(optimize, iterations: int, checkpoint: bytes | None = None, **choices: str):
    settings = api.JobSettings(api.SceneInput("k", "s.xml", {}, {}, "s.xml"), [],
                               [api.ParameterSetting(RED, 0.05, 0.0, 1.0),
                                api.ParameterSetting(GREEN, 0.05, 0.0, 1.0)],
                               iterations=iterations, spp=4, choices=choices)
    scene = _scene()
    image = mi.render(scene, spp=256, seed=99)
    refs = {0: optimize.Reference(mi.TensorXf(np.asarray(image)[..., :3]), None, "ref")}
    start = {RED: np.full(3, 0.2), GREEN: np.full(3, 0.8)}
    return optimize.Optimization(_scene(), settings, refs, initial=start,
                                 checkpoint=checkpoint)


def test_a_job_recovers_two_colours_and_goes_on_from_a_checkpoint_as_uninterrupted(optimize):
    truth = {k: np.asarray(mi.traverse(_scene())[k]).ravel() for k in (RED, GREEN)}
    whole = _job(optimize, 10, gauss_newton="on")
    steps = [whole.step() for _ in range(10)]
    last = steps[-1].values
    for key in (RED, GREEN):  # from 0.35-0.7 off to within the noise of 4 spp
        assert np.abs(last[key] - truth[key]).max() < 0.06, (key, last[key], truth[key])
    status = {c.name: c for c in whole.status()}["gauss_newton"]
    assert status.on and "10 steps" in status.why
    # Adam alone, at its rate, is still far off after as many iterations.
    adam = _job(optimize, 10)
    plain = [adam.step() for _ in range(10)][-1].values
    assert np.abs(plain[GREEN] - truth[GREEN]).max() > 0.2

    first = _job(optimize, 10, gauss_newton="on")
    before = [first.step() for _ in range(5)]
    again = _job(optimize, 10, first.checkpoint(), gauss_newton="on")
    after = [again.step() for _ in range(5)]
    for a, b in zip(before + after, steps):
        assert a.loss == pytest.approx(b.loss, rel=1e-4)
        for key in (RED, GREEN):
            np.testing.assert_allclose(a.values[key], b.values[key], rtol=1e-4, atol=1e-6)
