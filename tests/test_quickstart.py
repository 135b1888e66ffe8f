"""The README's quick start, run as it stands: its block of commands, against a daemon, from a
folder holding the scenes it names as a checkout does. The job must recover the colour and
roughness its reference was rendered with."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

TRUTH = {"bunny.bsdf.base_color.value": [0.7, 0.35, 0.2], "bunny.bsdf.roughness.value": [0.3]}


def quick_start_block() -> str:
    """The first ```sh block under the README's "### Quick start" heading."""
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("\n### Quick start\n"):]
    return re.search(r"```sh\n(.*?)```", section, re.DOTALL).group(1)


def test_the_readme_quick_start_runs_as_written(daemon, tmp_path):
    shutil.copytree(ROOT / "scenes", tmp_path / "scenes")
    env = {**os.environ, "MATOPT_SERVER": daemon.address,
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    env.pop("MATOPT_TOKEN", None)
    out = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", quick_start_block()],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    recovered = json.loads((tmp_path / "result" / "parameters.json").read_text())["parameters"]
    for key, truth in TRUTH.items():
        assert recovered[key] == pytest.approx(truth, abs=0.05), key
    assert "bunny.bsdf.base_color.value:" in out.stdout  # what 'job result' printed
