"""The CLI driving a real daemon through a whole session, across a daemon restart."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import time

import pytest

from conftest import Daemon
from scenes import write_mesh_scene

KEY = "shape_0.bsdf.reflectance.value"


@pytest.fixture
def own_daemon(tmp_path):
    d = Daemon(tmp_path / "data").start()
    yield d
    d.stop()


def matopt(daemon, *args, check=True) -> subprocess.CompletedProcess:
    env = dict(os.environ, MATOPT_SERVER=daemon.address)
    out = subprocess.run([sys.executable, "-m", "matopt_client.cli", *args], capture_output=True,
                         text=True, env=env, timeout=600)
    if check and out.returncode != 0:
        raise AssertionError(f"matopt {' '.join(args)} exited {out.returncode}:\n{out.stderr}")
    return out


def as_json(daemon, *args):
    return json.loads(matopt(daemon, *args, "--json").stdout)


def wait_for(daemon, job, states, timeout=120):
    deadline = time.time() + timeout
    while time.time() < deadline:
        status = as_json(daemon, "job", "status", job)
        if status["state"] in states:
            return status
        time.sleep(0.2)
    raise AssertionError(f"{job} never reached {states}: {status}")


def test_session_across_restart(own_daemon, tmp_path):
    d = own_daemon
    scene = matopt(d, "scene", "load", str(write_mesh_scene(tmp_path / "bundle")),
                   "--set", "res=32").stdout.strip()
    assert scene.startswith("scenes/")
    params = {p["key"]: p for p in as_json(d, "scene", "params", scene)["parameters"]}
    truth = params[KEY]["value"]
    assert truth == pytest.approx([0.2, 0.4, 0.6])

    matopt(d, "scene", "render", scene, "--out", str(tmp_path / "ref"), "--spp", "64")
    ref = tmp_path / "ref" / "sensor0_render.exr"
    assert ref.exists()

    # A finished job, waited for with a progress display.
    done = matopt(d, "job", "start", scene, "--ref", str(ref), "--param", KEY,
                  "--init", f"{KEY}=0.8,0.8,0.8", "--iterations", "60", "--min-error", "0",
                  "--spp-from", "40:32", "--wait", "--truth", f"{KEY}=0.2,0.4,0.6")
    job = done.stdout.strip().splitlines()[0]
    # What the daemon applied, its defaults included; how the job ended, each word once.
    applied = next(line for line in done.stderr.splitlines() if line.startswith(f"{job}: "))
    assert "loss mse, schedule cosine, " in applied
    assert "60 iterations at 16 spp, 32 spp from iteration 40" in applied
    assert f"{job} SUCCEEDED after 60 iterations; best loss " in done.stderr
    status = as_json(d, "job", "status", job)
    assert status["state"] == "JOB_STATE_SUCCEEDED" and status["iteration"] == 60
    history = as_json(d, "job", "history", job)["iterations"]
    errors = [r["errors"][0]["maxAbs"] for r in history]
    assert errors[0] == pytest.approx(0.6, abs=1e-5) and errors[-1] < 0.05  # 0.8 -> 0.2
    assert [r["spp"] for r in history] == [16] * 40 + [32] * 20

    out = tmp_path / "export"
    matopt(d, "job", "export", job, "--out", str(out), "--which", "last")
    exported = json.loads((out / "parameters.json").read_text())
    assert exported["parameters"][KEY] == pytest.approx(truth, abs=0.05)
    rows = list(csv.DictReader(open(out / "history.csv")))
    assert [int(r["iteration"]) for r in rows] == list(range(60))
    assert all(float(r["seconds"]) > 0 for r in rows)
    for role in ("initial", "optimized", "reference", "error"):
        assert (out / f"sensor0_{role}.png").read_bytes().startswith(b"\x89PNG")

    # A restart from where it ended, with other settings.
    restart = as_json(d, "job", "start", scene, "--ref", "blobs/" + status["spec"]["references"][0]
                    ["blob"].removeprefix("blobs/"), "--param", KEY, "--iterations", "2",
                    "--from", job, "--from-which", "last")
    assert restart["spec"]["parameters"][0]["initialValue"] == pytest.approx(
        exported["parameters"][KEY], abs=1e-6)
    wait_for(d, restart["name"], ("JOB_STATE_SUCCEEDED",))

    # A long job: watch a few events, pause, resume, then stop the daemon under it.
    long_job = matopt(d, "job", "start", scene, "--ref", str(ref), "--param", KEY,
                      "--init", f"{KEY}=0.8,0.8,0.8", "--min-error", "0",
                      "--iterations", "100000").stdout.strip()
    wait_for(d, long_job, ("JOB_STATE_RUNNING",))
    # The state the request leads to, whether or not an iteration was under way.
    assert "PAUSED" in matopt(d, "job", "pause", long_job).stdout
    paused = wait_for(d, long_job, ("JOB_STATE_PAUSED",))
    # Its standard errors on request: the person at the terminal is told they are under way.
    asked = matopt(d, "job", "result", long_job, "--which", "last", "--estimate")
    assert (f"estimating the standard errors of {long_job}'s last iteration on a worker"
            in asked.stderr), asked.stderr
    assert " +- " in asked.stdout and "standard errors: 3 components" in asked.stdout, \
        asked.stdout
    matopt(d, "job", "resume", long_job)
    wait_for(d, long_job, ("JOB_STATE_RUNNING",))
    time.sleep(1.5)  # past a checkpoint (every 10 iterations)
    assert d.restart() and d.proc.poll() is None

    # Everything is still there after the restart.
    status = as_json(d, "job", "status", job)
    assert status["state"] == "JOB_STATE_SUCCEEDED"
    again = tmp_path / "export-again"
    matopt(d, "job", "export", job, "--out", str(again), "--which", "last")
    assert json.loads((again / "parameters.json").read_text()) == exported
    assert (again / "history.csv").read_text() == (out / "history.csv").read_text()

    interrupted = as_json(d, "job", "status", long_job)
    assert interrupted["state"] == "JOB_STATE_INTERRUPTED"
    stopped_at = interrupted["iteration"]
    assert stopped_at > paused["iteration"]
    matopt(d, "job", "resume", long_job)
    resumed = wait_for(d, long_job, ("JOB_STATE_RUNNING",))
    assert resumed["resumedFrom"].startswith("checkpoint at iteration ")
    checkpoint = int(resumed["resumedFrom"].rsplit(" ", 1)[1])
    assert 0 < checkpoint <= stopped_at

    watch = subprocess.Popen([sys.executable, "-m", "matopt_client.cli", "--server", d.address, "job",
                              "watch", long_job, "--json"], stdout=subprocess.PIPE, text=True)
    first = json.loads(watch.stdout.readline())
    assert first["job"]["state"] == "JOB_STATE_RUNNING"
    assert "iteration" in json.loads(watch.stdout.readline())
    matopt(d, "job", "cancel", long_job)
    events = [json.loads(line) for line in watch.stdout]  # the stream ends on the final state
    assert watch.wait(timeout=60) != 0  # a cancelled job is not a success
    assert events[-1]["job"]["state"] == "JOB_STATE_CANCELLED"
    cancelled = wait_for(d, long_job, ("JOB_STATE_CANCELLED",))
    assert cancelled["iteration"] >= checkpoint
    listed = {j["name"]: j["state"] for j in as_json(d, "job", "list")["jobs"]}
    assert listed == {job: "JOB_STATE_SUCCEEDED", restart["name"]: "JOB_STATE_SUCCEEDED",
                      long_job: "JOB_STATE_CANCELLED"}


def test_errors_are_one_line_and_exit_nonzero(own_daemon, tmp_path):
    out = matopt(own_daemon, "job", "status", "jobs/doesnotexist", check=False)
    assert out.returncode == 1
    assert out.stderr.strip().count("\n") == 0 and "NOT_FOUND" in out.stderr
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene><oops></scene>")
    out = matopt(own_daemon, "scene", "load", str(bad), check=False)
    assert out.returncode != 0 and "malformed XML" in out.stderr and "Traceback" not in out.stderr
