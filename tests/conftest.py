"""Fixtures: real daemons on ephemeral loopback ports, procedural scenes, and stubs.

Daemons run as subprocesses (``python -m matoptd``) exactly as users start them, so tests see
the real command line, signals, restarts and on-disk state.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import grpc
import pytest

from matopt_api.v1 import matopt_pb2 as pb
from matopt_api.v1 import matopt_pb2_grpc as rpc

HERE = Path(__file__).parent
ROOT = HERE.resolve().parent
sys.path.insert(0, str(HERE))

TOKENS = {"alice": "alice-token-0123456789", "bob": "bob-token-0123456789ab"}


def token_file(folder: Path, users: dict[str, str] = TOKENS) -> Path:
    """A --tokens file in ``folder``: one "<token> <user>" line per user."""
    path = folder / "tokens"
    path.write_text("".join(f"{t} {u}\n" for u, t in users.items()))
    return path


DATA_DIRS: list[Path] = []  # every test daemon's
MESSAGES: list[str] = []    # every error message a call through ``Stubs`` received


class Daemon:
    """A matoptd process; ``restart()`` keeps its data dir."""

    def __init__(self, data_dir: Path, tokens: Path | None = None, *extra: str) -> None:
        self.data_dir, self.tokens, self.extra = data_dir, tokens, list(extra)
        DATA_DIRS.append(data_dir)
        self.proc: subprocess.Popen | None = None
        self.port = 0
        self.log = data_dir.parent / f"{data_dir.name}.log"

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    def start(self) -> "Daemon":
        port_file = self.data_dir.parent / f"{self.data_dir.name}.port"
        port_file.unlink(missing_ok=True)
        cmd = [sys.executable, "-m", "matoptd", "--listen", "127.0.0.1:0",
               "--data-dir", str(self.data_dir), "--port-file", str(port_file)]
        if self.tokens:
            cmd += ["--tokens", str(self.tokens)]
        cmd += self.extra
        self.proc = subprocess.Popen(cmd, stdout=open(self.log, "ab"), stderr=subprocess.STDOUT)
        deadline = time.time() + 120
        while not port_file.exists():
            if self.proc.poll() is not None:
                raise RuntimeError(f"matoptd exited: {self.log.read_text()[-2000:]}")
            if time.time() > deadline:
                self.proc.kill()  # else it outlives the test that never got to stop it
                self.proc.wait()
                raise RuntimeError("matoptd did not start in 120 s")
            time.sleep(0.1)
        self.port = int(port_file.read_text())
        return self

    def stop(self) -> int:
        if self.proc and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=120)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode if self.proc else 0

    def restart(self) -> "Daemon":
        self.stop()
        return self.start()


class Stubs:
    """The four services on one channel, sending a token when given one."""

    def __init__(self, address: str, token: str | None = None) -> None:
        self.channel = grpc.insecure_channel(address)
        self.metadata = (("authorization", f"Bearer {token}"),) if token else ()
        for name, stub in (("blobs", rpc.BlobServiceStub), ("scenes", rpc.SceneServiceStub),
                           ("jobs", rpc.JobServiceStub), ("server", rpc.ServerServiceStub)):
            setattr(self, name, _WithMetadata(stub(self.channel), self.metadata))

    def close(self) -> None:
        self.channel.close()


class _WithMetadata:
    def __init__(self, stub, metadata) -> None:
        self._stub, self._metadata = stub, metadata

    def __getattr__(self, name):
        method = getattr(self._stub, name)

        def call(request, **kw):
            try:
                return method(request, metadata=self._metadata, **kw)
            except grpc.RpcError as exc:
                MESSAGES.append(exc.details() or "")
                raise
        return call


@pytest.fixture
def no_server_paths():
    """After the test: no error message it received names a daemon's data directory (as
    given, absolute or resolved) or a worker's cache."""
    seen = len(MESSAGES)
    yield
    paths = {str(form) for d in DATA_DIRS for form in (d, d.absolute(), d.resolve())}
    for message in MESSAGES[seen:]:
        assert "worker-cache" not in message, message
        for path in paths:
            assert path not in message, message


@pytest.fixture(scope="session")
def node_tools() -> Path:
    """clients/examples/node with its npm packages (grpc-js, proto-loader, buf) installed
    at the lock file's versions: the example clients and the API's lint and breaking checks
    use them."""
    folder = ROOT / "clients" / "examples" / "node"
    if not shutil.which("npm"):
        pytest.skip("needs Node.js and npm")
    # As its README says: exactly the lock file's packages, which it never rewrites.
    subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=folder, check=True,
                   capture_output=True, timeout=600)
    return folder


@pytest.fixture(scope="session")
def daemon(tmp_path_factory) -> Daemon:
    d = Daemon(tmp_path_factory.mktemp("daemon") / "data").start()
    yield d
    d.stop()


@pytest.fixture(scope="session")
def stubs(daemon) -> Stubs:
    s = Stubs(daemon.address)
    yield s
    s.close()


@pytest.fixture
def cli_env(daemon) -> dict[str, str]:
    env = dict(os.environ, MATOPT_SERVER=daemon.address)
    env.pop("MATOPT_TOKEN", None)
    return env


def wait_state(stubs: Stubs, name: str, states, timeout: float = 300) -> pb.Job:
    deadline = time.time() + timeout
    while time.time() < deadline:
        job = stubs.jobs.GetJob(pb.GetJobRequest(name=name))
        if job.state in states:
            return job
        time.sleep(0.05)
    raise AssertionError(f"{name} did not reach {states}: {job}")


def finished(stubs: Stubs, spec: pb.JobSpec) -> tuple[pb.Job, pb.JobResult]:
    """A job run to its end (it must succeed), and its best result."""
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=spec))
    done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), timeout=600)
    assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
    return done, stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name))


def wait_iteration(stubs: Stubs, name: str, at_least: int, timeout: float = 180) -> pb.Job:
    """Until the job has done ``at_least`` iterations."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        job = stubs.jobs.GetJob(pb.GetJobRequest(name=name))
        if job.iteration >= at_least:
            return job
        time.sleep(0.05)
    raise AssertionError(f"{name} did not reach iteration {at_least}: {job}")
