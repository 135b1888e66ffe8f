"""The thesis's Tables 2 and 4 on their procedural analogues (tests/thesis_scenes.py: a
displaced-sphere PLY in a procedural EXR sky), small and fast: the daemon with its defaults
must recover the parameters the images decide, and say so where they do not.
bench/thesis_tables.py runs the full-size cases over several seeds."""

from __future__ import annotations

import numpy as np

from matopt_api.v1 import matopt_pb2 as pb

import thesis_scenes as ts
from test_materials import recover


def _run(stubs, case: ts.Case, iterations: int, **spec):
    truth = [dict(key=k, value=list(v)) for k, v in case.truth.items()]
    return recover(stubs, case.files, case.main,
                   {k: list(np.ravel(v)) for k, v in case.start.items()}, iterations,
                   spp=16, reference_spp=512,
                   ground_truth=[pb.ParameterValue(**t) for t in truth], **spec)


def test_table2_principled_blob_recovers_color_transmission_and_eta(stubs):
    """Principled blob (thesis Table 2): base_color, spec_trans and eta from the thesis's
    starts (0.1 / 0.02 / 1.54), roughness from 0.5 toward 0.01.

    Roughness below ~0.07 (alpha 0.005, a lobe far narrower than a pixel at 48 px) changes the
    image less than the noise of an iteration, so it is not asserted near 0.01: the job must
    have brought it down from 0.5, and its floor (alpha 0.001) must be reachable."""
    case = ts.table2(res=48)
    params, got, done = _run(stubs, case, iterations=60)
    assert done.integrator == "prb"
    for key in case.tolerance:
        if key.endswith("roughness.value"):
            continue
        error = ts.relative_error(key, got[key], case.truth[key])
        assert error < 0.04, (key, got[key], error)
    roughness = f"{ts.BSDF}.roughness.value"
    assert got[roughness][0] < 0.2, got[roughness]
    assert params[roughness].min ** 2 < 0.00102  # the floor is within 2% in alpha


def test_table3_glass_with_a_texture_from_black_recovers_spec_trans_and_eta(stubs):
    """Bump-mapped glass whose base_color is a texture started black (thesis Table 3). From
    black every lobe the texture tints is black and spec_trans fell to 0 in 5 iterations; the
    job starts the texture at 0.5 and says so. eta's AD gradient through prb's detached
    sampling had a random sign here; its central difference brings it within 5% (0.1% in
    trials at this size)."""
    case = ts.table3(res=32)
    params, got, done = _run(stubs, case, iterations=60)
    for key, tol in case.tolerance.items():
        error = ts.relative_error(key, got[key], case.truth[key])
        assert error < tol, (key, got[key], error)
    texture = f"{ts.BSDF}.nested_bsdf.base_color.data"
    eta = f"{ts.BSDF}.nested_bsdf.eta"
    assert any(n.startswith(f"{texture}: started at 0.5 instead of black") for n in done.notes)
    assert any(n.startswith(f"{eta}: its gradient by central differences") for n in done.notes)
    # The texture comes back in part (a single 32 px view through glass): its error against
    # the truth ends below that of the grey it started from.
    truth = case.truth[texture]
    assert np.sqrt(np.mean((got[texture] - truth) ** 2)) < np.sqrt(np.mean((0.5 - truth) ** 2))


def test_table4_rough_dielectric_with_medium_recovers_albedo_sigma_t_and_eta(stubs):
    """Rough dielectric blob around a homogeneous medium (thesis Table 4), from the thesis's
    starts (albedo 0.01, sigma_t 0.99, eta 1.55, alpha 0.98), eta's range as listed (no user
    clamp at 1.55 as the thesis needed).

    At this size (32 px, 60 iterations) the medium is still on its way (its rate is 0.03):
    albedo ended 8-9% off in trials, sigma_t 9-13% (albedo and sigma_t trade off: a denser,
    brighter medium looks alike), eta within 1.5%; bench/thesis_tables.py runs 48 px and 100
    iterations. alpha is not asserted: below ~0.1 the blur it adds to the refraction is
    under a pixel here."""
    case = ts.table4(res=32)
    params, got, done = _run(stubs, case, iterations=60)
    assert done.integrator == "prbvolpath"
    assert params[f"{ts.BSDF}.eta"].max >= 4
    tolerance = {f"{ts.MEDIUM}.albedo.value.value": 0.15,
                 f"{ts.MEDIUM}.sigma_t.value.value": 0.2, f"{ts.BSDF}.eta": 0.03}
    for key, tol in tolerance.items():
        error = ts.relative_error(key, got[key], case.truth[key])
        assert error < tol, (key, got[key], error)
