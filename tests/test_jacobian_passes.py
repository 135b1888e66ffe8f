"""The standard errors' Jacobian takes one render pass per component, but a colour's three
components share one pass where the render keeps colour channels apart (engine/jacobian.py,
``_passes``): each component's column must then be exactly what its own pass gives, and a
scene that mixes channels must not be packed. Both of a column's estimates come from one pass
at twice the samples where the integrator allows (engine/split_samples.py): they must be
independent and unbiased, as two passes of their own are. At a job's end the passes run in
pieces with other jobs' work between them: the same estimate as in one go."""

from __future__ import annotations

import gc
import time

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

PAUSE = 1000.0  # seconds another job's turn takes between the estimate's pieces


@pytest.fixture(scope="module")
def rgb():
    mi.set_variant("llvm_ad_rgb")
    from matoptd.engine import jacobian
    return jacobian


def _cornell(size: int = 32):
    scene = mi.cornell_box()
    scene["sensor"]["film"]["width"] = scene["sensor"]["film"]["height"] = size
    scene = mi.load_dict(scene)
    return scene, mi.traverse(scene)


def test_a_colours_packed_pass_gives_each_component_its_own_column(rgb):
    scene, params = _cornell()
    integrator = mi.load_dict({"type": "prb", "max_depth": 4})
    key = "red.reflectance.value"
    q = rgb.Quantity(key, np.array(params[key], dtype=np.float64).ravel(), False, 0.0, 1.0)
    assert rgb._passes([0, 1, 2], rgb.components([q], {}), {key: q}, params) == [[0, 1, 2]]

    packed = rgb._columns(scene, params, integrator, "prb", q, [0, 1, 2], 0, 16, (7, 8),
                          [q], None)
    for c in range(3):
        own = rgb._columns(scene, params, integrator, "prb", q, [c], 0, 16, (7, 8), [q],
                           None)
        for n in (0, 1):
            scale = np.abs(own[n][0]).max()
            assert scale > 0  # the red wall is seen: its colour has a slope
            assert np.abs(own[n][0][..., np.arange(3) != c]).max() <= 1e-6 * scale
            np.testing.assert_allclose(packed[n][c], own[n][0], atol=1e-5 * scale)


@pytest.mark.parametrize("tint", [0.0, 0.5])
def test_a_principled_base_colour_is_packed_only_without_a_tint(rgb, tint):
    scene = mi.load_dict({
        "type": "scene",
        "ball": {"type": "sphere", "bsdf": {"type": "principled", "spec_tint": tint,
                                            "base_color": {"type": "rgb",
                                                           "value": [0.8, 0.3, 0.2]}}},
        "light": {"type": "constant"},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8,
                                                   "height": 8}}})
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("base_color.value"))
    q = rgb.Quantity(key, np.array(params[key], dtype=np.float64).ravel(), False, 0.0, 1.0)
    passes = rgb._passes([0, 1, 2], rgb.components([q], {}), {key: q}, params)
    assert passes == ([[0, 1, 2]] if tint == 0 else [[0], [1], [2]])


def test_every_forward_quantity_in_every_pass_changes_no_column(rgb):
    """Each pass makes all forward-mode quantities leaves (tangent 0 but for the one moved),
    so that every pass runs one compiled kernel: the others' zero tangents add nothing."""
    scene, params = _cornell()
    integrator = mi.load_dict({"type": "prb", "max_depth": 4})
    red, green = (rgb.Quantity(k, np.array(params[k], dtype=np.float64).ravel(), False, 0.0,
                               1.0) for k in ("red.reflectance.value", "green.reflectance.value"))
    for q in (red, green):
        for split in (False, True):
            traced = (lambda: rgb.split_samples.trace(scene, integrator, 0, 16, 5)
                      if split else None)
            alone = rgb._columns(scene, params, integrator, "prb", q, [0, 1, 2], 0, 16, (5, 6),
                                 [q], traced())
            both = rgb._columns(scene, params, integrator, "prb", q, [0, 1, 2], 0, 16, (5, 6),
                                [red, green], traced())
            for a, b in zip(sum(alone, []), sum(both, [])):
                assert np.abs(a).max() > 0
                np.testing.assert_allclose(b, a, atol=1e-5 * np.abs(a).max())


def test_two_estimates_from_one_pass_are_independent_and_unbiased(rgb):
    """sum(J_A J_B) over the pixels estimates sum(J^2) without J's noise only when A and B are
    independent: from one split pass, over many seeds, it must agree with two passes of their
    own and with a reference of 16384 samples, and the split renders with mi.render."""
    scene, params = _cornell()
    integrator = mi.load_dict({"type": "prb", "max_depth": 4})
    q = rgb.Quantity("red.reflectance.value",
                     np.array(params["red.reflectance.value"], dtype=np.float64).ravel(), False,
                     0.0, 1.0)
    split, apart = [], []
    for seed in range(24):
        traced = rgb.split_samples.trace(scene, integrator, 0, 4, 100 + seed)
        a, b = rgb._columns(scene, params, integrator, "prb", q, [0], 0, 4, (0, 0), [q],
                            traced)
        split.append(float(np.sum(a[0] * b[0])))
        a, b = rgb._columns(scene, params, integrator, "prb", q, [0], 0, 4,
                            (200 + seed, 300 + seed), [q], None)
        apart.append(float(np.sum(a[0] * b[0])))
    ref = rgb._columns(scene, params, integrator, "prb", q, [0], 0, 8192, (1, 2), [q], None)
    truth = float(np.sum(ref[0][0] * ref[1][0]))
    error = np.hypot(np.std(split), np.std(apart)) / np.sqrt(len(split))
    assert abs(np.mean(split) - np.mean(apart)) < 4 * error, (split, apart)
    assert abs(np.mean(split) - truth) < 4 * np.std(split) / np.sqrt(len(split)) + 0.01 * truth
    # the primal's halves: each a render of the same image at 256 spp
    first, second = rgb.split_samples.primal(
        rgb.split_samples.trace(scene, integrator, 0, 256, 9), integrator)
    image = np.array(mi.render(scene, integrator=integrator, spp=1024, seed=3))[..., :3]
    for half in (first, second):
        assert abs(half.mean() / image.mean() - 1) < 0.01


def _glass_and_texture():
    """A textured quad behind a rough glass ball (prb): a colour, a texture's modes and a
    dielectric's eta (by differences) in one J."""
    texels = np.random.default_rng(3).uniform(0.2, 0.8, (8, 8, 3)).astype(np.float32)
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "prb", "max_depth": 4},
        "sensor": {"type": "perspective", "fov": 35, "to_world": mi.ScalarTransform4f().look_at(
            origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 24, "height": 24, "rfilter": {"type": "box"}}},
        "light": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "ball": {"type": "sphere", "radius": 0.6, "bsdf": {"type": "roughdielectric",
                                                           "alpha": 0.2, "int_ior": 1.5}},
        "side": {"type": "sphere", "center": [1.1, 0.8, 0], "radius": 0.4, "bsdf": {
            "type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.4, 0.2]}}},
        "quad": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -1])
                 @ mi.ScalarTransform4f().scale(1.6), "bsdf": {"type": "diffuse", "reflectance": {
                     "type": "bitmap", "filter_type": "nearest", "bitmap": mi.Bitmap(texels)}}}})


def _held(rgb, monkeypatch):
    """The glass-and-texture scene as a job leaves it for J (Renders.holding: the values
    assigned), its quantities (a colour, the texture's modes, an eta differenced), a
    reference and a job of 8 spp; J at the job's spp in one round, whatever the timings, so
    that two estimates draw the same samples."""
    from matoptd.engine import parameters
    scene = _glass_and_texture()
    params = mi.traverse(scene)
    integrator = mi.load_dict({"type": "prb", "max_depth": 4})
    quantities = [
        rgb.Quantity("side.bsdf.reflectance.value",
                     np.array(params["side.bsdf.reflectance.value"], np.float64).ravel(),
                     False, 0.0, 1.0),
        rgb.Quantity("quad.bsdf.reflectance.data",
                     np.array(params["quad.bsdf.reflectance.data"], np.float64).ravel(), False,
                     0.0, 1.0, channels=3, shape=(8, 8, 3)),
        rgb.Quantity("ball.bsdf.eta", np.array([1.5]), True, 1.0, 2.0, difference=True,
                     eta=True)]
    reference = np.array(mi.render(scene, spp=64, seed=4))[..., :3]
    for q in quantities:
        params[q.key] = parameters.assign(params[q.key], q.value)
    params.update()
    monkeypatch.setattr(rgb, "_samples", lambda budget, passes, cost, spp: spp)
    monkeypatch.setattr(rgb, "SIGNAL", 0.0)
    return (scene, params, integrator, quantities, {0: rgb.Sensor(reference, None)},
            rgb.Job("mse", 8, 3, False, 100.0))


def test_frozen_passes_give_the_unfrozen_estimate(rgb, monkeypatch):
    """J's passes frozen (split_samples.Frozen: recorded once per sensor and spp, replayed
    for each component's tangent and seed) give the unfrozen J^T J, noise and standard
    errors, for a colour (forward mode, packed), a texture's modes and an eta (differences)."""
    from matoptd.engine import uncertainty
    scene, params, integrator, quantities, sensors, job = _held(rgb, monkeypatch)
    out = {}
    for freeze in (False, True):
        lin = rgb.linearize(scene, params, integrator, "prb", quantities, sensors, job, freeze)
        out[freeze] = lin, uncertainty.estimate(lin, quantities, sensors, job, None)
    (plain, plain_se), (frozen, frozen_se) = out[False], out[True]
    assert len(plain.components) == 3 + 9 + 1 and plain.notes == []
    assert frozen.notes and frozen.notes[0].startswith("standard errors: J's passes frozen")
    assert "carried outside" in frozen.notes[0]  # the texture's data: derived at update()
    for name in ("hessian", "noise", "reference", "spread"):
        a, b = getattr(plain.fit, name), getattr(frozen.fit, name)
        assert np.abs(a).max() > 0
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-5 * np.abs(a).max())
    assert plain_se.errors.keys() == frozen_se.errors.keys() and plain_se.errors
    assert np.all(np.isfinite(plain_se.errors["side.bsdf.reflectance.value"].error))
    for key, e in plain_se.errors.items():
        np.testing.assert_allclose(frozen_se.errors[key].error, e.error, rtol=1e-4)
        assert frozen_se.errors[key].reading == e.reading
    # parameters are back at their values afterwards
    for q in quantities:
        np.testing.assert_allclose(np.array(params[q.key]).ravel(), q.value, rtol=1e-6)


def test_an_estimate_in_pieces_with_other_work_between_is_the_estimate_in_one_go(
        rgb, monkeypatch):
    """At a job's end J's passes run as turns of the worker: another job renders its own
    scene between them. The pieces give the J^T J, noise and standard errors of one go, and
    the pauses between them are not the estimate's time (its budget is of its own)."""
    from matoptd.engine import uncertainty
    scene, params, integrator, quantities, sensors, job = _held(rgb, monkeypatch)
    # Another job's scene, rendered between pieces. Loaded (and rendered) before the estimate
    # in one go, and earlier tests' scenes collected, so that both see the same live BSDFs:
    # one more or less changes the passes' kernels, which are then traced again.
    other = mi.load_dict(mi.cornell_box())
    mi.render(other, spp=4, seed=1)
    gc.collect()
    whole = rgb.linearize(scene, params, integrator, "prb", quantities, sensors, job)
    # Each pause moves the clock the estimate reads on by PAUSE: counted, it would show.
    real, moved, pauses = time.perf_counter, [0.0], 0
    monkeypatch.setattr(time, "perf_counter", lambda: real() + moved[0])
    pieces = rgb.linearizing(scene, params, integrator, "prb", quantities, sensors, job)
    while True:
        try:
            next(pieces)
        except StopIteration as done:
            parts = done.value
            break
        mi.render(other, spp=4, seed=1)
        moved[0] += PAUSE
        pauses += 1
    assert pauses >= 3  # a pause after each of several passes
    for name in ("hessian", "noise", "reference", "spread"):
        a, b = getattr(whole.fit, name), getattr(parts.fit, name)
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-5 * np.abs(a).max())
    a = uncertainty.estimate(whole, quantities, sensors, job, None)
    b = uncertainty.estimate(parts, quantities, sensors, job, None)
    for key, e in a.errors.items():
        np.testing.assert_allclose(b.errors[key].error, e.error, rtol=1e-4)
    assert parts.seconds < PAUSE
