"""Standard errors of recovered values, without ground truth, through a real daemon: each
result value comes with one per component, read as its interval says; what the images do not
decide is said, never NaN; a gain is estimated with the parameters; a texture gets its mean
level. The calibration (does the truth lie within two standard errors as often as it should)
is tests/test_calibration.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import wait_state
from scenes import exr, upload

RES = 24
WALLS = {"red.reflectance.value": [0.570068, 0.0430135, 0.0443706],
         "green.reflectance.value": [0.105421, 0.37798, 0.076425]}
LIGHT = "light.emitter.radiance.value"


@pytest.fixture(scope="module")
def cornell(stubs):
    """The built-in Cornell box at RES px and a 256-spp render of it (EXR blob)."""
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(
        overrides={"resx": str(RES), "resy": str(RES)}))
    image = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=256)).images[0]
    return scene, image.exr_blob


def run(stubs, job_spec: pb.JobSpec) -> tuple[pb.Job, pb.JobResult]:
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=job_spec))
    done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), timeout=600)
    assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
    return done, stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name))


def test_each_wall_colour_comes_with_a_standard_error(stubs, cornell):
    scene, reference = cornell
    done, result = run(stubs, pb.JobSpec(
        scene=scene.name, references=[pb.Reference(blob=reference)], iterations=40, spp=8,
        parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3) for k in WALLS]))
    for p in result.parameters:
        assert len(p.standard_error) == len(p.value) == 3, p
        # A dark channel (truth 0.04) may end on the range's bound 0 at this size: then its
        # interval is one-sided, above the bound.
        assert list(p.interval) == [pb.INTERVAL_AT_LOWER_BOUND if v == 0 else
                                    pb.INTERVAL_TWO_SIDED for v in p.value], p
        # A 24 px view at 8 spp pins a wall's colour to a few percent, not to 1e-5 or 0.3.
        assert all(1e-3 < e < 0.1 for e in p.standard_error), p
    # GetJob shows the best result's values with the same standard errors.
    shown = {p.key: p for p in done.best_parameters}
    assert set(shown) == set(WALLS)
    for p in result.parameters:
        assert list(shown[p.key].standard_error) == list(p.standard_error)


def test_a_light_and_a_gain_that_only_scale_together_are_not_determined(stubs, cornell):
    """With fit_exposure, the light's radiance and the gain scale the same image: only their
    product is decided. Both are said to be not determined (+inf, never NaN), by name, while
    a wall's colour, which changes the image's pattern, keeps a finite standard error."""
    scene, reference = cornell
    done, result = run(stubs, pb.JobSpec(
        scene=scene.name, references=[pb.Reference(blob=reference, filename="box.exr")],
        iterations=30, spp=8, fit_exposure=True,
        parameters=[pb.ParameterSpec(key=LIGHT),
                    pb.ParameterSpec(key="red.reflectance.value", initial_value=[0.5] * 3)]))
    values = {p.key: p for p in result.parameters}
    light = values[LIGHT]
    assert list(light.interval) == [pb.INTERVAL_NOT_DETERMINED] * 3
    assert all(math.isinf(e) and e > 0 for e in light.standard_error)
    [gain] = result.gains
    assert list(gain.interval) == [pb.INTERVAL_NOT_DETERMINED] * 3
    red = values["red.reflectance.value"]
    assert all(np.isfinite(red.standard_error)) and not any(np.isnan(red.standard_error))
    note = next(n for n in done.notes if n.startswith("not determined by these images"))
    assert LIGHT in note and "gain of box.exr" in note
