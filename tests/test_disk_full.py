"""A full disk: RESOURCE_EXHAUSTED, jobs held (not failed, not lost), health NOT_SERVING, and
everything going on by itself once space is freed. The daemon's data dir is a small tmpfs."""

from __future__ import annotations

import errno
import subprocess
import time

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from matopt_api.v1 import matopt_pb2 as pb

from conftest import Daemon, Stubs, TOKENS, token_file, wait_state
from test_faults import cornell_job, wait_iteration

pytestmark = pytest.mark.faults


# 48 MiB: less than the data directory would need free under a fixed threshold of 64 MiB.
@pytest.fixture(params=["256m", "48m"])
def small_disk(tmp_path, request):
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={request.param}", "tmpfs",
                           str(mount)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip()}): needs root")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


def fill(path) -> None:
    """Writes zeros until the file system refuses more."""
    with open(path, "wb") as f:
        try:
            while True:
                f.write(b"\0" * (1 << 20))
                f.flush()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC


def health(address: str) -> int:
    channel = grpc.insecure_channel(address)
    try:
        return health_pb2_grpc.HealthStub(channel).Check(
            health_pb2.HealthCheckRequest(service=""), timeout=5).status
    finally:
        channel.close()


def wait_health(address: str, status: int, timeout: float = 60) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if health(address) == status:
            return
        time.sleep(0.2)
    raise AssertionError(f"health did not become {status}")


def test_a_full_disk_holds_jobs_and_recovers_by_itself(small_disk, tmp_path):
    """Whatever the disk's size: health SERVING again within seconds of space returning."""
    tokens = token_file(tmp_path)
    daemon = Daemon(small_disk / "data", tokens).start()
    alice, bob = Stubs(daemon.address, TOKENS["alice"]), Stubs(daemon.address, TOKENS["bob"])
    try:
        job = cornell_job(bob, 200)
        wait_iteration(bob, job.name, 12)
        filler = small_disk / "filler"
        fill(filler)

        wait_health(daemon.address, health_pb2.HealthCheckResponse.NOT_SERVING)
        with pytest.raises(grpc.RpcError) as err:
            alice.scenes.CreateScene(pb.CreateSceneRequest())
        assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "disk is full" in err.value.details()
        held = bob.jobs.GetJob(pb.GetJobRequest(name=job.name))  # reads still answer
        assert held.state == pb.JOB_STATE_RUNNING
        time.sleep(2)
        assert bob.jobs.GetJob(pb.GetJobRequest(name=job.name)).iteration <= held.iteration + 1

        filler.unlink()
        wait_health(daemon.address, health_pb2.HealthCheckResponse.SERVING, timeout=10)
        done = wait_state(bob, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), timeout=300)
        assert done.state == pb.JOB_STATE_SUCCEEDED, done
        history = bob.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=job.name)).iterations
        assert [r.iteration for r in history] == list(range(200))
        assert alice.scenes.CreateScene(pb.CreateSceneRequest()).name.startswith("scenes/")
    finally:
        daemon.stop()
