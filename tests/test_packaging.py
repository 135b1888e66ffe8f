"""The distribution as a user installs it: the wheel and the sdist that `python -m build`
makes, the client wheel in a fresh virtual environment without mitsuba or drjit, and a job run
from it against a daemon."""

from __future__ import annotations

import subprocess
import sys
import tarfile
import venv
import zipfile

import pytest

from conftest import ROOT, Daemon

pytestmark = pytest.mark.packaging

DISTRIBUTION = "matopt_mitsuba"  # `matopt` on the package index is another project


@pytest.fixture(scope="module")
def dist(tmp_path_factory):
    out = tmp_path_factory.mktemp("dist")
    built = subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(out),
                            str(ROOT)], capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stdout[-3000:] + built.stderr[-3000:]
    return out


def test_wheel_and_sdist_carry_the_contract(dist):
    wheel = next(dist.glob(f"{DISTRIBUTION}-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    for module in ("matopt_client/cli/__init__.py", "matoptd/console.py",
                   "matopt_api/v1/matopt_pb2.py", "matopt_api/v1/matopt.proto",
                   "matopt_api/enums.py"):
        assert module in names, module
    # `matopt/` is the package of the index's project `matopt`: no file of ours may be there.
    assert not [n for n in names if n.startswith("matopt/")]
    metadata = zipfile.ZipFile(wheel).read(
        next(n for n in names if n.endswith("/METADATA"))).decode()
    assert f"Name: {DISTRIBUTION.replace('_', '-')}" in metadata
    assert "Requires-Dist: mitsuba" in metadata and "extra == \"daemon\"" in metadata
    sdist = next(dist.glob(f"{DISTRIBUTION}-*.tar.gz"))
    members = tarfile.open(sdist).getnames()
    assert any(m.endswith("proto/matopt/v1/matopt.proto") for m in members)


def test_wheel_and_sdist_carry_the_license(dist):
    """The BSD licence's text travels with both, as its clause 2 asks of binary forms."""
    text = (ROOT / "LICENSE").read_bytes()
    assert b"BSD 3-Clause License" in text and b"the matopt authors" in text
    wheel = zipfile.ZipFile(next(dist.glob(f"{DISTRIBUTION}-*.whl")))
    names = wheel.namelist()
    metadata = wheel.read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    assert "License-Expression: BSD-3-Clause" in metadata
    assert "License-File: LICENSE" in metadata
    licenses = [n for n in names if n.endswith(".dist-info/licenses/LICENSE")]
    assert licenses, names
    assert wheel.read(licenses[0]) == text
    sdist = tarfile.open(next(dist.glob(f"{DISTRIBUTION}-*.tar.gz")))
    top = sdist.getnames()[0].split("/")[0]
    assert sdist.extractfile(f"{top}/LICENSE").read() == text


def test_client_wheel_alone_runs_a_job(dist, tmp_path):
    env_dir = tmp_path / "client-venv"
    venv.create(env_dir, with_pip=True)
    python = env_dir / "bin" / "python"
    wheel = next(dist.glob(f"{DISTRIBUTION}-*.whl"))
    installed = subprocess.run([str(python), "-m", "pip", "install", "-q", str(wheel)],
                               capture_output=True, text=True, timeout=600)
    assert installed.returncode == 0, installed.stderr[-3000:]
    for renderer in ("mitsuba", "drjit"):  # the base install is the client side only
        probe = subprocess.run([str(python), "-c", f"import {renderer}"], capture_output=True)
        assert probe.returncode != 0, f"{renderer} was installed with the client wheel"

    helped = subprocess.run([str(env_dir / "bin" / "matopt"), "--help"], capture_output=True,
                            text=True, timeout=120)
    assert helped.returncode == 0 and "scene" in helped.stdout and "job" in helped.stdout
    # The daemon's command is there too, and says in one line what it lacks.
    refused = subprocess.run([str(env_dir / "bin" / "matoptd")], capture_output=True,
                             text=True, timeout=120)
    assert refused.returncode == 2, refused.stderr
    assert refused.stderr.count("\n") == 1 and "Traceback" not in refused.stderr
    assert refused.stderr.startswith("matoptd: error: this install has the clients only "
                                     "(missing mitsuba, drjit, ")
    assert refused.stderr.rstrip().endswith('pip install "matopt-mitsuba[daemon]"')

    d = Daemon(tmp_path / "data", None).start()
    try:
        out = subprocess.run([str(env_dir / "bin" / "matopt"), "demo", "--server", d.address,
                              "--resolution", "32", "--iterations", "30",
                              "--out", str(tmp_path / "demo")],
                             capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stdout + out.stderr
        assert "SUCCEEDED after 30 iterations" in out.stderr
        error = float(out.stdout.split("max abs error ")[1].split()[0])
        assert error < 0.15, out.stdout  # the walls' colours, recovered by the wheel's client
    finally:
        d.stop()
