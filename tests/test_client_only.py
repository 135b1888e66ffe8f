"""The client package works where mitsuba and drjit are not installed (a laptop)."""

from __future__ import annotations

import subprocess
import sys

BLOCK = ("import sys\n"
         "for m in ('mitsuba', 'drjit', 'matoptd'):\n"
         "    sys.modules[m] = None  # any import of them now raises ImportError\n")


def run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", BLOCK + code], capture_output=True, text=True,
                          timeout=120)


def test_cli_help_without_mitsuba_or_drjit():
    for args in ([], ["job", "start"], ["job", "export"], ["scene", "load"], ["demo"]):
        out = run(f"from matopt_client.cli import main\nsys.argv = {['matopt', *args, '--help']!r}\n"
                  "main()")
        assert out.returncode == 0, out.stderr
        assert "Usage: " in out.stdout


def test_client_library_and_stubs_import_without_mitsuba_or_drjit():
    out = run("import matopt_client.client, matopt_client.export, matopt_api.v1.matopt_pb2_grpc\n"
              "assert 'mitsuba' not in [m for m in sys.modules if sys.modules[m] is not None]\n")
    assert out.returncode == 0, out.stderr


def test_unreachable_server_is_one_clear_line():
    out = run("from matopt_client.cli import main\n"
              "sys.argv = ['matopt', '--server', '127.0.0.1:1', 'job', 'list']\nmain()")
    assert out.returncode == 1
    assert out.stderr.strip().startswith("matopt: error: cannot reach matoptd at 127.0.0.1:1")
    assert "Traceback" not in out.stderr
