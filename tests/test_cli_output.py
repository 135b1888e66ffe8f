"""What the ``matopt`` command prints: the progress bar and the tables fitted to 60, 80 and
120 columns, the state a pause or cancel leads to, how a job ended, the settings the daemon
applied, loss names as ``--loss`` spells them, the default port, and a closed pipe.

Most run the CLI in-process against a fake client answering from memory; the closed pipe
runs it as a process against a real daemon.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from collections import Counter
from types import SimpleNamespace

import pytest
from click.testing import CliRunner

from matopt_api.v1 import matopt_pb2 as pb
from matopt_client import client as mc
from matopt_client import workflow
from matopt_client.cli import cli
from matopt_client.cli import job as cli_job
from matopt_client.cli import scene as cli_scene
from matopt_client.cli.progress import JobProgress, outcome

WIDTHS = (60, 80, 120)
KEYS = ["shape_0.bsdf.base_color.value", "shape_0.bsdf.roughness.value",
        "bunny_with_a_long_id.bsdf.reflectance.data"]
FILLED = pb.JobSpec(scene="scenes/0123456789ab", loss=pb.LOSS_DUAL_BUFFER, iterations=100,
                    spp=16, min_error=0, schedule=pb.SCHEDULE_COSINE,
                    sensor_mode=pb.SENSOR_MODE_ACCUMULATE,
                    parameters=[pb.ParameterSpec(key=k) for k in KEYS])


def job(iteration: int = 37, total: int = 100, state: int = pb.JOB_STATE_RUNNING,
        **fields) -> pb.Job:
    spec = pb.JobSpec()
    spec.CopyFrom(FILLED)
    spec.iterations = total
    out = pb.Job(name="jobs/0123456789ab", state=state, iteration=iteration, spec=spec,
                 loss=0.5, best_iteration=iteration - 1, best_loss=0.25,
                 elapsed_seconds=1.5, **fields)
    out.create_time.seconds = 1_800_000_000
    return out


class FakeClient:
    """What the commands below touch of a client, answering from memory."""

    def __init__(self, answer: pb.Job | None = None) -> None:
        self.info = pb.ServerInfo(losses=["mse", "dual_buffer"], schedules=["cosine"],
                                  sensor_modes=["accumulate"])
        answer = answer or job()
        history = [pb.IterationRecord(iteration=i, seconds=0.1 * i, loss=0.5 / (i + 1),
                                      errors=[pb.ParameterError(key=KEYS[0], rmse=0.01,
                                                                psnr=40, correlation=[0.9])])
                   for i in range(3)]
        self.jobs = SimpleNamespace(
            GetJob=lambda request: answer, PauseJob=lambda request: answer,
            CancelJob=lambda request: answer, ResumeJob=lambda request: answer,
            ListJobs=lambda request: pb.ListJobsResponse(jobs=[answer, job(3, 4000)]),
            GetJobHistory=lambda request: pb.GetJobHistoryResponse(iterations=history))
        self.scenes = SimpleNamespace(
            ListSceneParameters=lambda request: pb.ListSceneParametersResponse(parameters=[
                pb.Parameter(key=KEYS[0], kind=pb.PARAMETER_KIND_RGB, shape=[3],
                             value=[0.5, 0.25, 0.125], min=0, max=1, default_learning_rate=0.1),
                pb.Parameter(key=KEYS[1], kind=pb.PARAMETER_KIND_SCALAR, shape=[1], value=[0.5],
                             min=0.01, max=1, default_learning_rate=0.2, discontinuous=True),
                pb.Parameter(key=KEYS[2], kind=pb.PARAMETER_KIND_TEXTURE,
                             shape=[1200, 1200, 3], min=0, max=1, default_learning_rate=0.01)]))


def run(monkeypatch, args: list[str], answer: pb.Job | None = None, width: int = 120):
    fake = FakeClient(answer)
    for module in (cli_job, cli_scene):
        monkeypatch.setattr(module, "connected", lambda: fake)
    return CliRunner().invoke(cli, args, env={"COLUMNS": str(width)})


def printed(text: str) -> Counter:
    """The characters shown, wherever wrapping put them."""
    return Counter("".join(text.split()))


@pytest.mark.parametrize("width", WIDTHS)
def test_progress_keeps_its_bar_within_the_width(width):
    progress = JobProgress(interactive=False)
    running = job(370, 1000)
    running.loss, running.best_loss, running.elapsed_seconds = 0.0123457, 0.0111111, 1234.5
    progress(pb.JobEvent(job=running))
    line = progress.line(width - 1)
    assert len(line) <= width - 1, line
    assert len(line.split("|")[1]) >= 10, line  # the bar
    assert line.startswith("RUNNING  37%|") and "| 370/1000, loss 0.0123457" in line
    # The best loss is left out only where it would squeeze the bar.
    assert "1234.5 s" in line and ("best mean 0.0111111 at 369" in line) == (width >= 120)


def test_progress_names_the_iteration_its_best_is_from():
    """A loss below the best beside it reads as what it is: an iteration newer than the
    daemon's last ranking, or a single loss beside a windowed mean."""
    progress = JobProgress(interactive=False)
    mse = job(37, 100)
    mse.spec.loss = pb.LOSS_MSE
    progress(pb.JobEvent(job=mse))
    progress(pb.JobEvent(iteration=pb.IterationRecord(iteration=37, loss=0.125, seconds=2)))
    line = progress.line(79)
    assert "38/100, loss 0.125  2.0 s  best 0.25 at 36" in line, line
    mse.iteration, mse.best_iteration, mse.best_loss = 38, 37, 0.125  # the daemon ranks 37
    progress(pb.JobEvent(job=mse))
    assert "loss 0.5  1.5 s  best 0.125 at 37" in progress.line(79)
    progress(pb.JobEvent(job=job(38, 100)))  # dual_buffer: the daemon ranks a windowed mean
    assert "best mean 0.25 at 37" in progress.line(79)


@pytest.mark.parametrize("width", WIDTHS)
def test_progress_on_a_terminal_rewrites_one_line(width, monkeypatch, capsys):
    monkeypatch.setattr(shutil, "get_terminal_size", lambda *a: os.terminal_size((width, 24)))
    progress = JobProgress(interactive=True)
    progress(pb.JobEvent(job=job(0, 10)))
    for i in range(10):
        progress(pb.JobEvent(iteration=pb.IterationRecord(iteration=i, loss=0.1, seconds=i)))
    err = capsys.readouterr().err
    assert "\n" not in err
    parts = [p for p in err.split("\r") if p]
    assert parts[-1].startswith("RUNNING 100%|") and "10/10" in parts[-1]
    assert all(len(p) < width for p in parts)


def test_progress_in_a_log_prints_one_line_per_tenth(capsys):
    progress = JobProgress(interactive=False)
    progress(pb.JobEvent(job=job(0, 10)))
    for i in range(10):
        progress(pb.JobEvent(iteration=pb.IterationRecord(iteration=i, loss=0.1, seconds=i)))
    done = job(10, 10, pb.JOB_STATE_SUCCEEDED)  # the daemon's best comes with the job
    progress(pb.JobEvent(job=done))
    progress.close()
    lines = capsys.readouterr().err.split("\n")
    assert "\r" not in "".join(lines) and lines[-1] == ""
    assert len(lines[:-1]) == 12  # the start, one per tenth of 10 iterations, the end
    assert lines[-2].startswith("SUCCEEDED 100%|")
    assert lines[-2].endswith("| 10/10, loss 0.5  1.5 s  best mean 0.25 at 9")
    assert all("best" not in line for line in lines[:-2])  # not computed from the records


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("command", [["scene", "params", "s"], ["job", "list"],
                                     ["job", "status", "j"], ["job", "history", "j"]])
def test_tables_fit_the_width_and_keep_every_character(monkeypatch, width, command):
    answer = job(notes=["parameter 'bunny_with_a_long_id.bsdf.reflectance.data' has "
                        "4,320,000 values: 66 MiB on the device, 49 MiB of worker memory"])
    out = run(monkeypatch, command, answer, width)
    assert out.exit_code == 0, out.output
    assert all(len(line) <= width for line in out.stdout.splitlines()), out.stdout
    wide = run(monkeypatch, command, answer, 1000).stdout  # nothing wrapped
    assert not printed(wide) - printed(out.stdout)  # wrapped, nothing cut
    names = {"params": KEYS, "list": ["jobs/0123456789ab"], "status": ["jobs/0123456789ab"],
             "history": []}[command[1]]
    assert all(name in out.stdout for name in names)  # what a row is about stays whole


def test_pause_and_cancel_print_the_state_they_lead_to(monkeypatch):
    out = run(monkeypatch, ["job", "pause", "j"], job())
    assert out.stdout.startswith("jobs/0123456789ab RUNNING, then PAUSED at its next "
                                 "iteration boundary; 'matopt job watch jobs/0123456789ab'")
    assert run(monkeypatch, ["job", "pause", "j"], job(state=pb.JOB_STATE_PAUSED)
               ).stdout == "jobs/0123456789ab PAUSED\n"
    pending = job(notes=["end phase: cancel requested: the job stops at its next iteration "
                         "boundary, then renders its result images"])
    out = run(monkeypatch, ["job", "cancel", "j"], pending)
    assert out.stdout.startswith("jobs/0123456789ab RUNNING, then CANCELLED at its next "
                                 "iteration boundary (cancel requested: the job stops")
    assert run(monkeypatch, ["job", "cancel", "j"], job(state=pb.JOB_STATE_CANCELLED)
               ).stdout == "jobs/0123456789ab CANCELLED\n"


def test_how_a_job_ended_says_each_thing_once(capsys):
    outcome(job(30, 30, pb.JOB_STATE_SUCCEEDED, stop_reason="iterations"))
    outcome(job(12, 30, pb.JOB_STATE_SUCCEEDED, stop_reason="min_error"))
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "jobs/0123456789ab SUCCEEDED after 30 iterations; best loss 0.25 at " \
                       "iteration 29"
    assert lines[1].startswith("jobs/0123456789ab SUCCEEDED after 12 iterations (the loss "
                               "fell below min error)")


def test_loss_names_are_spelled_as_the_option_takes_them(monkeypatch):
    out = run(monkeypatch, ["job", "status", "j"]).stdout
    assert "loss dual_buffer, schedule cosine, sensors accumulate, 100 iterations at 16 spp" \
        in out
    assert "DUAL_BUFFER" not in out and "COSINE" not in out


def test_job_start_sends_only_what_was_given_and_prints_what_the_daemon_applied(monkeypatch):
    sent = []

    def start_job(client, spec, refs, initial_from=None, on_upload=None, timeout=None):
        sent.append(spec)
        return job(0, 100, pb.JOB_STATE_QUEUED)  # the daemon's answer: the spec filled in

    monkeypatch.setattr(workflow, "start_job", start_job)
    out = run(monkeypatch, ["job", "start", "s", "--ref", "blobs/r", "--param", KEYS[0],
                            "--loss", "dual_buffer"])
    assert out.exit_code == 0, out.output
    assert out.stdout == "jobs/0123456789ab\n"
    assert "jobs/0123456789ab: loss dual_buffer, schedule cosine, sensors accumulate, " \
           "100 iterations at 16 spp, min error 0, seed 0" in out.stderr
    assert sent[0].loss == pb.LOSS_DUAL_BUFFER and not sent[0].schedule
    assert not any(sent[0].HasField(f) for f in ("iterations", "spp", "min_error"))


def test_an_address_without_a_port_gets_matoptds():
    assert mc.with_port("gpu-box") == "gpu-box:50051"
    assert mc.with_port("gpu-box:7") == "gpu-box:7"
    assert mc.with_port("[::1]") == "[::1]:50051" and mc.with_port("::1") == "[::1]:50051"
    assert mc.with_port("unix:/run/matoptd.sock") == "unix:/run/matoptd.sock"
    with socket.socket() as s:
        if s.connect_ex(("127.0.0.1", mc.DEFAULT_PORT)) == 0:
            pytest.skip("something listens on 127.0.0.1:50051 here")
    out = subprocess.run([sys.executable, "-m", "matopt_client.cli", "--server", "127.0.0.1",
                          "info"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 1
    assert out.stderr.startswith("matopt: error: cannot reach matoptd at 127.0.0.1:50051")


def test_a_closed_pipe_ends_quietly(daemon):
    """``matopt info | head -1``: the reader is gone before matopt writes."""
    proc = subprocess.Popen([sys.executable, "-m", "matopt_client.cli", "--server",
                             daemon.address, "info"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 0, err
    assert err == ""
