"""``matopt job report``: the CSV holds exactly the daemon's history, and the plots are PNGs."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import wait_state
from scenes import cornell_with_truth

WALLS = ["red.reflectance.value", "green.reflectance.value"]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def matopt(daemon, *args, env_extra=None) -> subprocess.CompletedProcess:
    env = dict(os.environ, MATOPT_SERVER=daemon.address, **(env_extra or {}))
    env.pop("MATOPT_TOKEN", None)
    return subprocess.run([sys.executable, "-m", "matopt_client.cli", *args], capture_output=True,
                          text=True, env=env, timeout=120)


@pytest.fixture(scope="module")
def two_jobs(stubs):
    """Two short jobs on a 32x32 Cornell box: one with ground truth, one without."""
    scene, truth, ref = cornell_with_truth(stubs, 32, 16, WALLS)

    def start(ground_truth: bool, spp: int) -> str:
        spec = pb.JobSpec(scene=scene.name, iterations=4, spp=spp, min_error=0,
                          references=[pb.Reference(blob=ref.exr_blob)],
                          parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3)
                                      for k in WALLS])
        if ground_truth:
            spec.ground_truth.extend(pb.ParameterValue(key=k, value=v) for k, v in truth.items())
        return stubs.jobs.CreateJob(pb.CreateJobRequest(spec=spec)).name

    names = [start(True, 2), start(False, 4)]
    for name in names:
        assert wait_state(stubs, name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), 120).state == pb.JOB_STATE_SUCCEEDED
    return names, truth


def test_report_csv_matches_history_and_plots_are_pngs(daemon, stubs, two_jobs, tmp_path):
    names, truth = two_jobs
    out = tmp_path / "report"
    done = matopt(daemon, "job", "report", *names, "--out", str(out), "--label", "with truth",
                  "--json")
    assert done.returncode == 0, done.stderr
    files = json.loads(done.stdout)["files"]
    assert sorted(os.path.basename(f) for f in files) == [
        "loss.png", "parameter_error.png", "report.csv"]

    with open(out / "report.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    error_columns = [f"relative_error:{k}" for k in WALLS]
    assert list(rows[0])[:6] == ["job", "label", "iteration", "seconds", "loss", "image_error"]
    psnr_columns = [f"psnr:{k}" for k in WALLS]
    assert sorted(list(rows[0])[6:]) == sorted(error_columns + psnr_columns)
    for name in names:
        history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=name)).iterations
        mine = [r for r in rows if r["job"] == name]
        assert [int(r["iteration"]) for r in mine] == [h.iteration for h in history] == [0, 1, 2, 3]
        assert [float(r["seconds"]) for r in mine] == [h.seconds for h in history]
        assert [np.float32(r["loss"]) for r in mine] == [np.float32(h.loss) for h in history]
        assert all(r["image_error"] == "" for r in mine)
    assert {r["label"] for r in rows if r["job"] == names[0]} == {"with truth"}
    assert all(r["label"].startswith(names[1].removeprefix("jobs/") + " (mse, 4 spp")
               for r in rows if r["job"] == names[1])

    # The job with ground truth has every parameter's error: the daemon's own, or computed
    # from the iteration's values; the one without has none.
    history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=names[0])).iterations
    for row, record in zip([r for r in rows if r["job"] == names[0]], history):
        values = {v.key: np.asarray(v.value) for v in record.parameters}
        for key, column in zip(WALLS, error_columns):
            t = np.asarray(truth[key])
            expected = np.sqrt(np.mean((values[key] - t) ** 2)) / np.sqrt(np.mean(t ** 2))
            assert float(row[column]) == pytest.approx(expected, rel=1e-3)
            rmse = np.sqrt(np.mean((values[key] - t) ** 2))
            assert float(row[f"psnr:{key}"]) == pytest.approx(
                20 * np.log10(np.abs(t).max() / rmse), abs=0.01)
    assert float(rows[0][error_columns[0]]) > 0.1  # from grey walls: far off at first
    assert all(r[c] == "" for r in rows if r["job"] == names[1] for c in error_columns)

    for png in ("loss.png", "parameter_error.png"):
        data = (out / png).read_bytes()
        assert data.startswith(PNG_SIGNATURE) and len(data) > 1000
        import matplotlib.image
        assert matplotlib.image.imread(out / png).shape[:2] == (500, 800)


def test_report_without_ground_truth_leaves_out_the_error_plot(daemon, two_jobs, tmp_path):
    names, _ = two_jobs
    done = matopt(daemon, "job", "report", names[1], "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["loss.png", "report.csv"]
    assert done.stdout.split() == [str(tmp_path / "report.csv"), str(tmp_path / "loss.png")]
    assert "no parameter errors" in done.stderr


def test_report_without_matplotlib_says_what_to_install(daemon, tmp_path):
    blocker = tmp_path / "site"
    (blocker / "matplotlib").mkdir(parents=True)
    (blocker / "matplotlib" / "__init__.py").write_text("raise ImportError('not installed')\n")
    done = matopt(daemon, "job", "report", "jobs/x", "--out", str(tmp_path / "out"),
                  env_extra={"PYTHONPATH": str(blocker)})
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "install matopt-mitsuba[plot]" in lines[0], done.stderr
    assert not (tmp_path / "out").exists()
