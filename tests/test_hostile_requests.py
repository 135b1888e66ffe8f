"""One user's expensive requests are refused before they reach a worker, with a message naming
the value, the limit and the flag; a cancel or a shutdown takes effect within seconds even
inside a long render; the other user's work goes on. Real daemons, two users."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time

import grpc
import pytest

from matopt_api.v1 import matopt_pb2 as pb
from matoptd.scheduling.monitor import CANCEL_GRACE_S, SHUTDOWN_GRACE_S

from conftest import Daemon, Stubs, TOKENS, token_file, wait_state
from scenes import upload
from test_faults import WALLS, cornell_job, two_users, wait_worker, worker  # noqa: F401

from test_image_headers import png_header_only

# Every message these tests receive is scanned for the daemon's own paths.
pytestmark = pytest.mark.usefixtures("no_server_paths")

# 32x32 px at 65536 spp: 2^26 samples, just within the default limit of a render call; one
# iteration (render and gradient) takes minutes on CPU cores, however many. Memory stays
# small: Mitsuba traces the samples in one kernel, without arrays of their size.
LONG_SPP = 65536


def rpc_error(call, *args) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as err:
        call(*args)
    return err.value


@pytest.fixture(scope="module")
def users(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    tokens = token_file(root)
    daemon = Daemon(root / "data", tokens, "--max-jobs-per-user", "2",
                    "--max-tasks-per-user", "1").start()
    alice, bob = Stubs(daemon.address, TOKENS["alice"]), Stubs(daemon.address, TOKENS["bob"])
    yield alice, bob
    alice.close()
    bob.close()
    daemon.stop()


@pytest.fixture(scope="module")
def bobs_job(users) -> pb.Job:
    """Bob's ordinary job, running while alice's requests are refused."""
    return cornell_job(users[1], 40)


@pytest.fixture(scope="module")
def cornell(users):
    alice = users[0]
    scene = alice.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "32",
                                                                      "resy": "32"}))
    ref = alice.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=4)).images[0]
    return scene, ref


def job_request(scene: pb.Scene, refs: list[pb.Reference], **spec) -> pb.CreateJobRequest:
    return pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, references=refs, parameters=[pb.ParameterSpec(key=k) for k in WALLS],
        **spec))


def test_a_job_at_a_million_spp_is_refused(users, bobs_job, cornell):
    alice = users[0]
    scene, ref = cornell
    err = rpc_error(alice.jobs.CreateJob, job_request(
        scene, [pb.Reference(blob=ref.exr_blob)], spp=1_000_000))
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "spp 1,000,000 on sensor 0's 32x32 px film is 1,024,000,000 samples in one render " \
           "call; the limit is 67,108,864 (matoptd --max-samples)" in err.details()


def test_render_scene_at_a_million_spp_is_refused(users, bobs_job, cornell):
    alice = users[0]
    scene, _ = cornell
    err = rpc_error(alice.scenes.RenderScene, pb.RenderSceneRequest(name=scene.name,
                                                                    spp=1_000_000))
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "spp 1,000,000 on sensor 0's 32x32 px film" in err.details()
    assert "(matoptd --max-samples)" in err.details()


def test_resolution_20000_is_refused_up_front(users, bobs_job, cornell):
    alice = users[0]
    scene, ref = cornell
    err = rpc_error(alice.jobs.CreateJob, job_request(
        scene, [pb.Reference(blob=ref.exr_blob, filename="ref.exr")], film_height=20000))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert ("sensor 0 would render a 20000x20000 px film (from film_height 20000 and reference "
            "'ref.exr' (32x32 px)): at most 8,192 px on a side (matoptd --max-film-side)"
            ) == err.details()


def test_a_very_wide_reference_is_refused_for_the_film_it_would_need(users, bobs_job, cornell):
    alice = users[0]
    scene, _ = cornell
    sha = upload(alice, png_header_only(100000, 1))
    err = rpc_error(alice.jobs.CreateJob, job_request(
        scene, [pb.Reference(blob=f"blobs/{sha}", filename="strip.png")], film_height=16))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "sensor 0 would render a 1600000x16 px film" in err.details()
    assert "reference 'strip.png' (100000x1 px)" in err.details()


def test_a_reference_over_the_pixel_limit_is_refused_from_its_header(users, bobs_job, cornell):
    alice = users[0]
    scene, _ = cornell
    sha = upload(alice, png_header_only(25000, 25000))
    err = rpc_error(alice.jobs.CreateJob, job_request(
        scene, [pb.Reference(blob=f"blobs/{sha}", filename="poster.png")]))
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert ("reference image 'poster.png' is a 25000x25000 px PNG file: 625,000,000 px; the "
            "limit is 67,108,864 px (matoptd --max-reference-pixels) (not retried: it holds "
            "until the usage or the limit changes)") == err.details()


def test_a_user_has_at_most_n_jobs_queued_or_running(users, bobs_job, cornell):
    alice = users[0]
    scene, ref = cornell
    small = job_request(scene, [pb.Reference(blob=ref.exr_blob)], iterations=100000, spp=1)
    first, second = alice.jobs.CreateJob(small), alice.jobs.CreateJob(small)
    err = rpc_error(alice.jobs.CreateJob, small)
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert err.details().startswith("user 'alice' has 2 queued or running jobs; the limit is 2 "
                                    "(matoptd --max-jobs-per-user)")
    alice.jobs.PauseJob(pb.PauseJobRequest(name=first.name))
    wait_state(alice, first.name, (pb.JOB_STATE_PAUSED,))
    third = alice.jobs.CreateJob(small)  # a paused job holds no place
    err = rpc_error(alice.jobs.ResumeJob, pb.ResumeJobRequest(name=first.name))
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "(matoptd --max-jobs-per-user)" in err.details()
    for job in (first, second, third):
        alice.jobs.CancelJob(pb.CancelJobRequest(name=job.name))
    for job in (first, second, third):
        wait_state(alice, job.name, (pb.JOB_STATE_CANCELLED,))


def test_a_users_scene_requests_in_progress_are_limited(users, bobs_job, cornell):
    """With --max-tasks-per-user 1, of three renders sent at once one runs, the others are
    refused at once; bob's are his own."""
    alice, bob = users
    scene, _ = cornell
    start = threading.Barrier(3)
    outcomes: list = []

    def render() -> None:
        start.wait()
        try:
            alice.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=1024))
            outcomes.append("rendered")
        except grpc.RpcError as exc:
            outcomes.append(exc)

    threads = [threading.Thread(target=render) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    refusals = [o for o in outcomes if o != "rendered"]
    assert outcomes.count("rendered") >= 1 and refusals, outcomes
    for err in refusals:
        assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "user 'alice' already has 1 scene request(s)" in err.details()
        assert "(matoptd --max-tasks-per-user)" in err.details()


def test_the_other_users_job_ran_meanwhile(users, bobs_job):
    done = wait_state(users[1], bobs_job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED, pb.JOB_STATE_CANCELLED))
    assert done.state == pb.JOB_STATE_SUCCEEDED and done.iteration == 40, done


# -- a cancel or a shutdown inside a long render ----------------------------------------------

def long_job(stubs: Stubs) -> pb.Job:
    """A job in the first of its iterations, each of which takes minutes."""
    job = cornell_job(stubs, 3, spp=LONG_SPP)
    wait_state(stubs, job.name, (pb.JOB_STATE_RUNNING,), timeout=120)
    time.sleep(1.0)  # the load returned; the first iteration is under way
    return job


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.faults
def test_cancel_inside_a_long_iteration_stops_it_within_seconds(two_users):  # noqa: F811
    daemon, alice, bob = two_users()
    bob_scene = bob.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "16",
                                                                       "resy": "16"}))
    bob_ref = bob.scenes.RenderScene(pb.RenderSceneRequest(name=bob_scene.name, spp=4)).images[0]
    job = long_job(alice)
    busy = worker(alice)
    assert busy.state == pb.WORKER_STATE_BUSY and job.name in busy.jobs
    # Bob asks for a job now: its reference check waits for the worker.
    bobs: list = []
    asking = threading.Thread(target=lambda: bobs.append(bob.jobs.CreateJob(pb.CreateJobRequest(
        spec=pb.JobSpec(scene=bob_scene.name, iterations=5, spp=2,
                        references=[pb.Reference(blob=bob_ref.exr_blob)],
                        parameters=[pb.ParameterSpec(key=WALLS[0])])))))
    asking.start()

    sent = time.monotonic()
    asked = alice.jobs.CancelJob(pb.CancelJobRequest(name=job.name))
    answered = time.monotonic() - sent
    assert asked.state == pb.JOB_STATE_RUNNING, asked  # until it stops
    # Answered while bob's spec is checked beside the render, before the grace runs out.
    assert answered < CANCEL_GRACE_S, f"the cancel was answered after {answered:.1f} s"
    cancelled = wait_state(alice, job.name, (pb.JOB_STATE_CANCELLED, pb.JOB_STATE_FAILED, pb.JOB_STATE_SUCCEEDED), timeout=60)
    assert cancelled.state == pb.JOB_STATE_CANCELLED, cancelled
    # The grace, then a kill and a state written: seconds, against an iteration of minutes.
    # Timed by the job's record, from the cancel's arrival: the API runs at nice 19 beside
    # the render, so its calls wait for CPU (docs/engine.md).
    took = (cancelled.update_time.ToNanoseconds() - asked.update_time.ToNanoseconds()) / 1e9
    assert took < CANCEL_GRACE_S + 6.0, f"the cancel took {took:.1f} s"
    assert any("cancelled during a long iteration" in n for n in cancelled.notes)

    asking.join(timeout=120)
    assert bobs, "bob's CreateJob did not return"
    done = wait_state(bob, bobs[0].name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), timeout=120)
    assert done.state == pb.JOB_STATE_SUCCEEDED, done
    after = wait_worker(bob, (pb.WORKER_STATE_IDLE,))
    assert after.restarts == 1 and after.pid != busy.pid
    assert "its job was cancelled during a long iteration" in after.last_exit
    assert not alive(busy.pid)


@pytest.mark.faults
def test_sigterm_inside_a_long_iteration_exits_within_seconds(two_users):  # noqa: F811
    daemon, alice, bob = two_users()
    job = long_job(alice)
    busy = worker(alice)
    # A client watching the job, as the CLI and the Qt app do: its stream stays open.
    watch = alice.jobs.WatchJob(pb.WatchJobRequest(name=job.name))
    next(watch)

    began = time.monotonic()
    daemon.proc.send_signal(signal.SIGTERM)
    try:
        daemon.proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("the daemon did not exit within 60 s of SIGTERM")
    took = time.monotonic() - began
    assert daemon.proc.returncode == 0
    # The grace an iteration in flight gets, then seconds for the rest, against an
    # iteration of minutes.
    assert took < SHUTDOWN_GRACE_S + 10.0, f"the daemon took {took:.1f} s to exit"
    assert not alive(busy.pid), "the worker outlived the daemon"
    watch.cancel()

    daemon.start()
    alice = Stubs(daemon.address, TOKENS["alice"])
    after = alice.jobs.GetJob(pb.GetJobRequest(name=job.name))
    assert after.state == pb.JOB_STATE_INTERRUPTED, after
    # Marked by the shutdown itself, not found running by the next start.
    assert after.stop_reason.startswith("the daemon was shut down"), after.stop_reason
    alice.close()
