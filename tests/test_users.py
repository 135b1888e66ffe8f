"""Several users on one daemon: tokens, and nobody sees or controls another's work."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import grpc
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import TOKENS, Daemon, Stubs, wait_state

ROOT = Path(__file__).resolve().parent.parent
RUNNABLE = (pb.JOB_STATE_QUEUED, pb.JOB_STATE_RUNNING)


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    root = tmp_path_factory.mktemp("shared")
    tokens = root / "tokens"
    tokens.write_text("# token user\n" + "".join(f"{t} {u}\n" for u, t in TOKENS.items()))
    d = Daemon(root / "data", tokens).start()
    yield d
    d.stop()


def test_no_or_wrong_token_is_unauthenticated(shared):
    for token in (None, "not-a-real-token-at-all"):
        s = Stubs(shared.address, token)
        with pytest.raises(grpc.RpcError) as err:
            s.jobs.ListJobs(pb.ListJobsRequest())
        assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
        assert "Bearer" in err.value.details()
        s.close()


def test_health_needs_no_token(shared):
    from grpc_health.v1 import health_pb2, health_pb2_grpc
    channel = grpc.insecure_channel(shared.address)
    status = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=""))
    assert status.status == health_pb2.HealthCheckResponse.SERVING
    channel.close()


def test_health_lists_the_server_and_every_service(shared):
    from grpc_health.v1 import health_pb2, health_pb2_grpc
    with grpc.insecure_channel(shared.address) as channel:
        listed = health_pb2_grpc.HealthStub(channel).List(health_pb2.HealthListRequest(),
                                                         timeout=10)
    assert {name: s.status for name, s in listed.statuses.items()} == {
        name: health_pb2.HealthCheckResponse.SERVING
        for name in ("", "matopt.v1.BlobService", "matopt.v1.SceneService",
                     "matopt.v1.JobService", "matopt.v1.ServerService")}


def test_users_see_and_control_only_their_own_jobs(shared):
    alice, bob = Stubs(shared.address, TOKENS["alice"]), Stubs(shared.address, TOKENS["bob"])
    assert alice.server.GetServerInfo(pb.GetServerInfoRequest()).user == "alice"
    scene = alice.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "32", "resy": "32"}))
    ref = alice.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=8)).images[0]
    job = alice.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=100000, references=[pb.Reference(blob=ref.exr_blob)],
        parameters=[pb.ParameterSpec(key="red.reflectance.value")])))

    for call, req in ((bob.jobs.GetJob, pb.GetJobRequest(name=job.name)),
                      (bob.jobs.CancelJob, pb.CancelJobRequest(name=job.name)),
                      (bob.jobs.PauseJob, pb.PauseJobRequest(name=job.name)),
                      (bob.jobs.DeleteJob, pb.DeleteJobRequest(name=job.name)),
                      (bob.scenes.GetScene, pb.GetSceneRequest(name=scene.name)),
                      (bob.scenes.ListSceneParameters,
                       pb.ListSceneParametersRequest(name=scene.name))):
        with pytest.raises(grpc.RpcError) as err:
            call(req)
        assert err.value.code() == grpc.StatusCode.NOT_FOUND, call
    assert job.name not in [j.name for j in bob.jobs.ListJobs(pb.ListJobsRequest()).jobs]
    assert job.name in [j.name for j in alice.jobs.ListJobs(pb.ListJobsRequest()).jobs]
    # Bob's attempts changed nothing. A pause or cancel acts at an iteration boundary, a
    # fraction of a second later: the job must be seen running well past where it is now.
    at = alice.jobs.GetJob(pb.GetJobRequest(name=job.name)).iteration
    deadline = time.time() + 180
    while True:
        now = alice.jobs.GetJob(pb.GetJobRequest(name=job.name))
        if now.iteration >= at + 20 or now.state not in RUNNABLE or time.time() > deadline:
            break
        time.sleep(0.05)
    assert (now.state, now.iteration >= at + 20) == (pb.JOB_STATE_RUNNING, True), now
    alice.jobs.CancelJob(pb.CancelJobRequest(name=job.name))
    wait_state(alice, job.name, (pb.JOB_STATE_CANCELLED,))
    alice.close()
    bob.close()


def test_tokens_file_errors_name_the_line(tmp_path):
    bad = tmp_path / "tokens"
    bad.write_text("short alice\n")
    out = subprocess.run([sys.executable, "-m", "matoptd", "--tokens", str(bad), "--data-dir",
                          str(tmp_path / "d")], capture_output=True, text=True, timeout=60)
    assert out.returncode != 0
    assert f"{bad}:1: token for 'alice' is shorter than 16 characters" in out.stderr


def test_refuses_public_address_without_tokens(tmp_path):
    out = subprocess.run([sys.executable, "-m", "matoptd", "--listen", "0.0.0.0:0",
                          "--data-dir", str(tmp_path / "d")], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode != 0 and "without --tokens" in out.stderr


@pytest.mark.skipif(not shutil.which("openssl"), reason="needs openssl to make certificates")
def test_tls_with_the_deploy_certificates(tmp_path):
    """With --tls-cert/--tls-key the token only ever travels encrypted; clients need --tls-ca."""
    certs = tmp_path / "certs"
    subprocess.run(["bash", str(ROOT / "deploy" / "make-certs.sh"), "-o", str(certs),
                    "localhost", "127.0.0.1"], check=True, capture_output=True, timeout=120)
    tokens = tmp_path / "tokens"
    tokens.write_text(f"{TOKENS['alice']} alice\n")
    d = Daemon(tmp_path / "data", tokens, "--tls-cert", str(certs / "server.pem"),
               "--tls-key", str(certs / "server.key")).start()
    try:
        base = [sys.executable, "-m", "matopt_client.cli", "--server", d.address,
                "--token", TOKENS["alice"]]
        ok = subprocess.run(base + ["--tls-ca", str(certs / "ca.pem"), "info", "--json"],
                            capture_output=True, text=True, timeout=120)
        assert ok.returncode == 0, ok.stderr
        assert json.loads(ok.stdout)["user"] == "alice"
        plain = subprocess.run(base + ["info"], capture_output=True, text=True, timeout=120)
        assert plain.returncode != 0 and "cannot reach matoptd" in plain.stderr
    finally:
        d.stop()
