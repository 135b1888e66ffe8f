"""A request refused for a moment gets in, one refused for good fails at once: the daemon's
RESOURCE_EXHAUSTED carries RetryInfo and a retry pushback for a limit that lifts by itself,
a pushback of -1 for one that does not, and the client library's channel retries the first
only (gRPC's own retries, its service config). A real gRPC server in this process, with the
daemon's error interceptor; and the CLI in 10 processes against a real daemon."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import threading

import grpc
import pytest
from google.rpc import error_details_pb2
from grpc_status import rpc_status

from matopt_api.v1 import matopt_pb2 as pb
from matopt_api.v1 import matopt_pb2_grpc as rpc
from matopt_client.client import connect
from matoptd.errors import Busy, ResourceExhausted
from matoptd.server.admission import Limits, TaskSlots
from matoptd.server.interceptors import NOT_RETRIED, Errors

from conftest import Daemon
from scenes import write_mesh_scene

KEY = "shape_0.bsdf.reflectance.value"


class Refusing(rpc.JobServiceServicer):
    """GetJob refused ``refusals`` times with ``error``, then answered."""

    def __init__(self) -> None:
        self.calls, self.refusals, self.error = 0, 0, None
        self.attempts: list[str] = []  # grpc-previous-rpc-attempts of each call

    async def GetJob(self, request, context):
        self.calls += 1
        self.attempts.append(dict(context.invocation_metadata()).get(
            "grpc-previous-rpc-attempts", ""))
        if self.calls <= self.refusals:
            raise self.error
        return pb.Job(name="jobs/ok")


@pytest.fixture(scope="module")
def server():
    """A server on its own event loop in a thread; yields (address, servicer)."""
    servicer = Refusing()
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    holder = {}

    async def serve():
        s = grpc.aio.server(interceptors=[Errors(["matopt.v1.JobService"])])
        rpc.add_JobServiceServicer_to_server(servicer, s)
        holder["port"] = s.add_insecure_port("127.0.0.1:0")
        await s.start()
        holder["server"] = s
        ready.set()
        await s.wait_for_termination()

    thread = threading.Thread(target=loop.run_until_complete, args=(serve(),), daemon=True)
    thread.start()
    ready.wait(10)
    yield f"127.0.0.1:{holder['port']}", servicer
    loop.call_soon_threadsafe(lambda: loop.create_task(holder["server"].stop(None)))
    thread.join(10)


def ask(address: str, servicer: Refusing, error: Exception, refusals: int):
    servicer.calls, servicer.refusals, servicer.error = 0, refusals, error
    servicer.attempts = []
    client = connect(address, probe_timeout=None)
    try:
        return client.jobs.GetJob(pb.GetJobRequest(name="jobs/ok"), timeout=30)
    finally:
        client.close()


def test_a_limit_that_lifts_is_retried_after_the_delay_it_names(server):
    address, servicer = server
    answer = ask(address, servicer, Busy("too many requests in progress", 0.05), 3)
    assert answer.name == "jobs/ok" and servicer.calls == 4
    assert servicer.attempts == ["", "1", "2", "3"]  # the daemon doubles its delay with each


def test_a_limit_that_does_not_lift_fails_at_once_and_says_so(server):
    address, servicer = server
    with pytest.raises(grpc.RpcError) as err:
        ask(address, servicer, ResourceExhausted("your blobs use 2 MiB of your quota"), 3)
    assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert err.value.details() == "your blobs use 2 MiB of your quota" + NOT_RETRIED
    assert servicer.calls == 1  # not retried


def test_the_temporary_refusal_carries_retry_info(server):
    address, servicer = server
    servicer.calls, servicer.refusals = 0, 1
    servicer.error = Busy("too many requests in progress", 1.5)
    with grpc.insecure_channel(address) as channel:  # no retry policy: the refusal itself
        with pytest.raises(grpc.RpcError) as err:
            rpc.JobServiceStub(channel).GetJob(pb.GetJobRequest(name="jobs/ok"), timeout=10)
    status = rpc_status.from_call(err.value)
    assert status.code == grpc.StatusCode.RESOURCE_EXHAUSTED.value[0]
    info = error_details_pb2.RetryInfo()
    assert status.details[0].Unpack(info)
    assert info.retry_delay.ToMilliseconds() == 1500
    assert ("grpc-retry-pushback-ms", "1500") in err.value.trailing_metadata()


def test_task_slots_say_when_to_come_back_from_how_long_tasks_hold_them():
    t = [0.0]
    slots = TaskSlots(Limits(max_tasks_per_user=1), clock=lambda: t[0], spread=lambda: 0.5)
    for _ in range(20):  # tasks of 4 s each
        with slots.hold("alice"):
            t[0] += 4.0
    with slots.hold("alice"):
        with pytest.raises(Busy) as busy:
            with slots.hold("alice"):
                pass
        with slots.hold("bob"):  # another user's slot is their own
            pass
    assert busy.value.retry_after == pytest.approx(4.0, rel=0.01)
    assert "try again in a few seconds" in str(busy.value)


# -- a burst through the CLI -------------------------------------------------------------------

@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    root = tmp_path_factory.mktemp("burst")
    d = Daemon(root / "data", None, "--max-tasks-per-user", "2").start()
    yield d
    d.stop()


def matopt(daemon, *args) -> subprocess.Popen:
    env = dict(os.environ, MATOPT_SERVER=daemon.address)
    return subprocess.Popen([sys.executable, "-m", "matopt_client.cli", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_ten_jobs_started_at_once_by_one_user_all_exist(daemon, tmp_path):
    load = matopt(daemon, "scene", "load", str(write_mesh_scene(tmp_path / "bundle")),
                  "--set", "res=16")
    scene = load.communicate(timeout=300)[0].strip()
    assert load.returncode == 0 and scene.startswith("scenes/")
    render = matopt(daemon, "scene", "render", scene, "--out", str(tmp_path / "ref"), "--spp",
                    "16")
    render.communicate(timeout=300)
    ref = tmp_path / "ref" / "sensor0_render.exr"
    assert ref.exists()
    starts = [matopt(daemon, "job", "start", scene, "--ref", str(ref), "--param", KEY,
                     "--iterations", "2", "--spp", "2") for _ in range(10)]
    outcomes = [(p.communicate(timeout=600), p.returncode) for p in starts]
    failed = [err for (out, err), rc in outcomes if rc != 0]
    assert not failed, failed
    names = {out.strip().splitlines()[0] for (out, _), _ in outcomes}
    client = connect(daemon.address)
    try:
        listed = {j.name for j in client.jobs.ListJobs(pb.ListJobsRequest(page_size=100)).jobs}
    finally:
        client.close()
    assert len(names) == 10 and names <= listed
