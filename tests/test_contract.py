"""The API contract as other ecosystems meet it: `buf lint` (STANDARD, with the exceptions
written down in buf.yaml), `buf breaking` against the frozen v1, and server reflection under
both names, v1 (what newer tools ask first) and v1alpha."""

from __future__ import annotations

import subprocess

import pytest

from conftest import ROOT, Daemon

pytestmark = pytest.mark.examples


def buf(node_tools, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([str(node_tools / "node_modules" / ".bin" / "buf"), *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def test_buf_lint_passes(node_tools):
    out = buf(node_tools, "lint")
    assert out.returncode == 0, out.stdout + out.stderr


def test_no_breaking_change_against_the_frozen_v1(node_tools):
    out = buf(node_tools, "breaking", "--against", "proto/v1-frozen.binpb")
    assert out.returncode == 0, out.stdout + out.stderr


def test_breaking_check_catches_a_renamed_enum_value(node_tools, tmp_path):
    """The check is live: a copy of the contract with one value renamed fails it."""
    copy = tmp_path / "proto"
    (copy / "matopt" / "v1").mkdir(parents=True)
    (copy / "buf.yaml").write_text("version: v2\n")  # a module of its own
    text = (ROOT / "proto" / "matopt" / "v1" / "matopt.proto").read_text()
    (copy / "matopt" / "v1" / "matopt.proto").write_text(
        text.replace("JOB_STATE_PAUSED = 3", "JOB_STATE_ON_HOLD = 3"))
    out = subprocess.run([str(node_tools / "node_modules" / ".bin" / "buf"), "breaking",
                          str(copy), "--against", str(ROOT / "proto" / "v1-frozen.binpb")],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode != 0 and "JOB_STATE_PAUSED" in out.stdout, out.stdout + out.stderr


@pytest.mark.parametrize("protocol", ["grpc-v1", "grpc-v1alpha"])
def test_reflection_lists_the_services(node_tools, protocol, tmp_path):
    d = Daemon(tmp_path / "data", None).start()
    try:
        out = buf(node_tools, "curl", "--protocol", "grpc", "--http2-prior-knowledge",
                  "--reflect-protocol", protocol,
                  "--list-methods", f"http://{d.address}", timeout=120)
        assert out.returncode == 0, out.stderr
        methods = out.stdout.split()
        for m in ("matopt.v1.JobService/CreateJob", "matopt.v1.BlobService/UploadBlob",
                  "matopt.v1.ServerService/GetServerInfo"):
            assert m in methods, out.stdout
    finally:
        d.stop()
