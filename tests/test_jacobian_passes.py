"""The standard errors' Jacobian takes one render pass per component, but a colour's three
components share one pass where the render keeps colour channels apart (engine/jacobian.py,
``_passes``): each component's column must then be exactly what its own pass gives, and a
scene that mixes channels must not be packed. Both of a column's estimates come from one pass
at twice the samples where the integrator allows (engine/split_samples.py): they must be
independent and unbiased, as two passes of their own are."""

from __future__ import annotations

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")


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
