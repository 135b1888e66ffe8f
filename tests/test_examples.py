"""The example clients in other languages (clients/examples/), run as a user would run them
against a real daemon: the Node.js client over TLS with a token, the grpcurl/buf curl
walk-through in plain text. Each must recover the plate's colour it rendered as its reference.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess

import pytest

from conftest import ROOT, TOKENS, Daemon

pytestmark = pytest.mark.examples

EXAMPLES = ROOT / "clients" / "examples"


def recovered(out: subprocess.CompletedProcess) -> dict:
    assert out.returncode == 0, out.stdout + out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def assert_close(result: dict, tolerance: float = 0.05) -> None:
    error = max(abs(a - b) for a, b in zip(result["value"], result["truth"]))
    assert error < tolerance, result
    assert result["iterations"] == 40  # every history page was read


@pytest.mark.parametrize("system,cpu", [("linux", "x64"), ("linux", "arm64"),
                                        ("darwin", "arm64"), ("darwin", "x64"),
                                        ("win32", "x64")])
def test_npm_ci_takes_the_lock_file_on_every_platform(node_tools, tmp_path, system, cpu):
    """The lock file lists buf's build for each platform, so `npm ci` accepts it anywhere
    (a lock with this machine's build only fails with "Missing: ... from lock file")."""
    for name in ("package.json", "package-lock.json"):
        shutil.copy(node_tools / name, tmp_path / name)
    out = subprocess.run(["npm", "ci", "--dry-run", "--ignore-scripts", "--no-audit",
                          "--no-fund", f"--os={system}", f"--cpu={cpu}"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    if not shutil.which("openssl"):
        pytest.skip("needs openssl to make certificates")
    out = tmp_path_factory.mktemp("certs")
    subprocess.run(["bash", str(ROOT / "deploy" / "make-certs.sh"), "-o", str(out),
                    "localhost", "127.0.0.1"], check=True, capture_output=True, timeout=120)
    return out


def test_node_client_over_tls_with_a_token(node_tools, certs, tmp_path):
    tokens = tmp_path / "tokens"
    tokens.write_text(f"{TOKENS['alice']} alice\n")
    d = Daemon(tmp_path / "data", tokens, "--tls-cert", str(certs / "server.pem"),
               "--tls-key", str(certs / "server.key")).start()
    try:
        out = subprocess.run(
            ["node", str(EXAMPLES / "node" / "walkthrough.js"), "--server", f"localhost:{d.port}",
             "--token", TOKENS["alice"], "--ca", str(certs / "ca.pem")],
            capture_output=True, text=True, timeout=600)
        result = recovered(out)
        assert_close(result)
        # The two errors it provokes come back with their codes and messages.
        assert "a job on an unknown key: INVALID_ARGUMENT: " in out.stderr
        assert "no.such.key" in out.stderr
        assert "a job that does not exist: NOT_FOUND: " in out.stderr
        # Without the token the daemon answers UNAUTHENTICATED and the client says so.
        refused = subprocess.run(
            ["node", str(EXAMPLES / "node" / "walkthrough.js"), "--server", f"localhost:{d.port}",
             "--ca", str(certs / "ca.pem")], capture_output=True, text=True, timeout=120)
        assert refused.returncode == 1 and "authorization" in refused.stderr.lower()
    finally:
        d.stop()


def without(*tools: str) -> str:
    """PATH without the folders that hold any of ``tools``."""
    return os.pathsep.join(d for d in os.environ["PATH"].split(os.pathsep)
                           if not any(os.path.exists(os.path.join(d, t)) for t in tools))


def test_curl_walkthrough_with_neither_grpcurl_nor_buf_installed(tmp_path):
    """As the README runs it, with nothing on PATH but what a Debian machine with Node.js
    has: buf comes through npx."""
    if not shutil.which("npx", path=without("grpcurl", "buf")):
        pytest.skip("needs Node.js's npx")
    d = Daemon(tmp_path / "data", None).start()
    try:
        env = {k: v for k, v in os.environ.items() if k != "BUF"}
        env["PATH"] = without("grpcurl", "buf")
        out = subprocess.run(["bash", str(EXAMPLES / "curl" / "walkthrough.sh"), d.address],
                             capture_output=True, text=True, timeout=600, env=env)
        result = recovered(out)
        assert_close(result)
        assert "a job on an unknown key: " in out.stderr and "no.such.key" in out.stderr
        assert "a job that does not exist: " in out.stderr
    finally:
        d.stop()
