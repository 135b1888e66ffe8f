"""What the frozen v1 API promises beyond single calls: GetJobHistory in pages with opaque
tokens, Delete answering google.protobuf.Empty, the choices jobs accept announced by
GetServerInfo, and a default stopping rule that runs a job to its end and says why it stopped.
"""

from __future__ import annotations

import base64

import grpc
import pytest
from google.protobuf import empty_pb2

from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb

from conftest import wait_state


@pytest.fixture(scope="module")
def cornell(stubs):
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "16", "resy": "16"}))
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=16)).images[0]
    return scene, ref


def run_job(stubs, cornell, **spec) -> pb.Job:
    scene, ref = cornell
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, references=[pb.Reference(blob=ref.exr_blob)], spp=2,
        parameters=[pb.ParameterSpec(key="red.reflectance.value", initial_value=[0.5] * 3)],
        **spec)))
    return wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))


def test_a_default_job_runs_all_its_iterations_and_says_why_it_stopped(stubs, cornell):
    done = run_job(stubs, cornell, iterations=12)
    assert done.spec.min_error == 0  # no loss threshold unless asked for
    assert (done.state, done.iteration, done.stop_reason) == (pb.JOB_STATE_SUCCEEDED, 12,
                                                                 "iterations")
    assert "stopped after all 12 iterations" in done.notes


def test_min_error_when_given_stops_early_and_the_note_says_so(stubs, cornell):
    done = run_job(stubs, cornell, iterations=50, min_error=10.0)  # any loss is below 10
    assert done.stop_reason == "min_error" and done.iteration < 50
    note = next(n for n in done.notes if n.startswith("stopped at iteration"))
    assert "fell below min_error 10" in note, done.notes


def test_history_comes_in_pages_with_opaque_tokens(stubs, cornell):
    done = run_job(stubs, cornell, iterations=20)
    pages, token = [], ""
    while True:
        page = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(
            name=done.name, page_size=7, page_token=token))
        pages.append([r.iteration for r in page.iterations])
        token = page.next_page_token
        if not token:
            break
        assert not token.isdigit()  # not an offset a client could come to rely on
    assert pages == [list(range(0, 7)), list(range(7, 14)), list(range(14, 20))]
    whole = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=done.name))
    assert len(whole.iterations) == 20 and not whole.next_page_token  # default page: 1,000

    forged = base64.urlsafe_b64encode(b"o:-3").decode()
    for bad in ("7", forged, "%%%"):
        with pytest.raises(grpc.RpcError) as err:
            stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=done.name, page_token=bad))
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert f"invalid page_token '{bad}'" in err.value.details()


def test_delete_answers_empty(stubs, cornell):
    done = run_job(stubs, cornell, iterations=2)
    assert stubs.jobs.DeleteJob(pb.DeleteJobRequest(name=done.name)) == empty_pb2.Empty()
    with pytest.raises(grpc.RpcError) as err:
        stubs.jobs.GetJob(pb.GetJobRequest(name=done.name))
    assert err.value.code() == grpc.StatusCode.NOT_FOUND


def test_server_info_announces_the_choices_by_short_name(stubs):
    info = stubs.server.GetServerInfo(pb.GetServerInfoRequest())
    assert info.losses == ["mse", "dual_buffer", "brightness_independent_mse", "mae",
                           "multiscale_mse"]
    assert info.schedules == ["cosine", "constant"]
    assert info.sensor_modes == ["accumulate", "step_per_sensor"]
    for name in info.losses:  # each parses back to a value of the contract
        assert enums.short_name(pb.Loss, enums.parse(pb.Loss, name)).lower() == name


def test_enum_short_names_round_trip():
    assert enums.parse(pb.JobState, "running") == pb.JOB_STATE_RUNNING
    assert enums.parse(pb.JobState, "JOB_STATE_PAUSED") == pb.JOB_STATE_PAUSED
    assert enums.short_name(pb.JobState, pb.JOB_STATE_SUCCEEDED) == "SUCCEEDED"
    assert enums.short_name(pb.JobState, 99) == "99"  # a newer daemon's value
    with pytest.raises(ValueError, match="unknown JobState 'sleeping': expected one of queued"):
        enums.parse(pb.JobState, "sleeping")
    with pytest.raises(ValueError):
        enums.parse(pb.JobState, "unspecified")
