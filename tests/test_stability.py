"""Stiff and extreme cases: the optimizer never produces a NaN parameter, never steps out of
physical validity, and says what went wrong when it cannot converge. (The slower cases, with
timings, are in bench/.)"""

from __future__ import annotations

import math

import pytest

from matopt_api.v1 import matopt_pb2 as pb

import stiff
from conftest import wait_state
from scenes import create_scene
from stiff import glass, sky


def job(stubs, xml: str, key: str, start, iterations: int, ref_spp: int = 64, **spec):
    scene = create_scene(stubs, {"s.xml": xml.encode()}, "s.xml")
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=ref_spp)).images[0]
    created = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=iterations, min_error=-1,
        references=[pb.Reference(blob=ref.exr_blob)],
        parameters=[pb.ParameterSpec(key=key, initial_value=start,
                                     **({"learning_rate": spec.pop("lr")} if "lr" in spec
                                        else {}))], **spec)))
    done = wait_state(stubs, created.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
    assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
    history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=created.name)).iterations
    values = [list(r.parameters[0].value) for r in history]
    assert all(math.isfinite(v) for vs in values for v in vs), "a NaN/Inf parameter"
    return done, values


@pytest.mark.parametrize("case", [c for c in stiff.CASES if c.fast], ids=lambda c: c.name)
def test_stiff_case(stubs, case):
    """Each case of tests/stiff.py: finite and in range at every iteration, and recovered within
    its tolerance or diagnosed (bench/stability.py tabulates the same cases)."""
    out = stiff.run(stubs, case)
    assert not stiff.verdict(case, out), (stiff.verdict(case, out), out.errors, out.final)


def test_all_black_reference(stubs):
    """Black is the infimum of a non-negative radiance: the value heads to 0 (slowly, as in the
    dark case), never below it, never NaN."""
    done, values = job(stubs, sky(0.0), "emitter_0.radiance.value", [1, 1, 1], 60, ref_spp=1,
                       lr=0.2)
    assert 0 < values[-1][0] < 0.1


@pytest.mark.parametrize("lr", [1e-5, 1.0])
def test_extreme_learning_rates_stay_finite_and_in_range(stubs, lr):
    done, values = job(stubs, glass(1.5), "ball.bsdf.alpha.value", [0.5], 20, lr=lr)
    assert all(0 <= v[0] <= 1 for v in values)
    if lr == 1e-5:  # nothing moves, and the job says why
        assert any(e in n for e in stiff.LOSS_DID_NOT_FALL for n in done.notes), done.notes


def test_principled_roughness_stops_at_the_alpha_floor_and_says_so(stubs):
    """Below 0.0316 the principled BSDF's alpha is floored: roughness is listed from 0.01 (the
    value stepped on may go below the floor), a start below 0.0318 shows as 0.0318, and a job
    that ends there says what that means."""
    key = "ball.bsdf.roughness.value"
    scene = create_scene(stubs, {"s.xml": stiff.principled_ball(0.01).encode()}, "s.xml")
    listed = {p.key: p for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name)).parameters}
    assert listed[key].min == pytest.approx(0.01)
    done, values = job(stubs, stiff.principled_ball(0.01), key, [0.0], 10, lr=1e-5)
    assert values[0][0] == pytest.approx(0.0318)
    assert any("alpha floor" in n and n.startswith(key) for n in done.notes), done.notes


def test_one_spp_dual_buffer_is_not_fooled_by_noise(stubs):
    """At 1 spp each dual-buffer estimate is mostly noise and often negative; the job neither
    stops on a lucky draw (min_error 0) nor reports one as its best."""
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "32",
                                                                      "resy": "32"}))
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=256)).images[0]
    created = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=120, min_error=0, spp=1, loss=pb.LOSS_DUAL_BUFFER,
        references=[pb.Reference(blob=ref.exr_blob)],
        parameters=[pb.ParameterSpec(key="red.reflectance.value",
                                     initial_value=[0.2, 0.2, 0.2])])))
    done = wait_state(stubs, created.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
    history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=created.name)).iterations
    assert min(r.loss for r in history) < 0  # single estimates do go negative
    assert done.best_iteration >= 7  # a mean over 8 iterations, never a single draw
    best = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=created.name))
    assert list(best.parameters[0].value)[0] > 0.35  # moved most of the way from 0.2 to 0.57
