"""The client workflow shared by the CLI and the Qt app, without a daemon: overrides, job specs,
the daemon's choices, the progress line on narrow terminals and in logs, sensor indices."""

from __future__ import annotations

import os
import re
import shutil
from types import SimpleNamespace

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")  # the Qt form, in one test

import pytest
from click.testing import CliRunner

from matopt_client import workflow
from matopt_client.cli import cli
from matopt_client.cli import job as cli_job
from matopt_api.v1 import matopt_pb2 as pb

INFO = pb.ServerInfo(losses=["mse", "dual_buffer", "mae", "newer_loss"],
                     schedules=["cosine", "constant"],
                     sensor_modes=["accumulate", "step_per_sensor"])


def test_override_items_and_their_errors_name_the_bad_item():
    items = workflow.split_overrides("resx=64, resy=64  albedo=0.5,0.5,0.5")
    assert workflow.parse_overrides(items) == {"resx": "64", "resy": "64",
                                               "albedo": "0.5,0.5,0.5"}
    for bad in ("resx", "=64"):
        with pytest.raises(ValueError, match=f"'{bad}' is not of the form NAME=VALUE"):
            workflow.parse_overrides(["spp=4", bad])


def test_spec_has_what_was_given_and_leaves_the_daemon_defaults_unset():
    spec = workflow.build_spec("scenes/s", [pb.ParameterSpec(key="k")],
                               workflow.JobSettings(loss="dual_buffer", iterations=7))
    assert (spec.scene, [p.key for p in spec.parameters]) == ("scenes/s", ["k"])
    assert (spec.loss, spec.iterations) == (pb.LOSS_DUAL_BUFFER, 7)
    assert not any(spec.HasField(f) for f in ("spp", "min_error", "learning_rate"))
    assert (spec.schedule, spec.sensor_mode, spec.seed, spec.clamp) == (0, 0, 0, False)
    with pytest.raises(ValueError, match="unknown Loss 'mean_bias_error'.*dual_buffer"):
        workflow.build_spec("scenes/s", [], workflow.JobSettings(loss="mean_bias_error"))


def test_restart_keeps_what_the_settings_leave_out_and_replaces_the_rest():
    old = pb.JobSpec(scene="scenes/s", seed=7, spp=4, loss=pb.LOSS_MAE, clamp=True,
                     parameters=[pb.ParameterSpec(key="old")],
                     references=[pb.Reference(blob="blobs/a")])
    spec = workflow.build_spec("scenes/s", [pb.ParameterSpec(key="new")],
                               workflow.JobSettings(spp=8, clamp=False), base=old)
    assert (spec.seed, spec.spp, spec.loss, spec.clamp) == (7, 8, pb.LOSS_MAE, False)
    assert [p.key for p in spec.parameters] == ["new"] and not spec.references
    assert workflow.settings_of(old).loss == "mae" and workflow.settings_of(old).seed == 7


def test_choices_are_the_daemons_lists():
    offered = workflow.choices(INFO)
    assert offered.losses == ("mse", "dual_buffer", "mae", "newer_loss")
    assert offered.sensor_modes == ("accumulate", "step_per_sensor")
    assert workflow.check_choice("loss", "MAE", offered.losses) == "mae"
    with pytest.raises(ValueError, match="unknown loss 'mean_bias_error': this daemon offers "
                                         "mse, dual_buffer, mae, newer_loss"):
        workflow.check_choice("loss", "mean_bias_error", offered.losses)


def test_references_keep_their_masks_and_upload_nothing_that_is_on_the_daemon(tmp_path):
    refs = workflow.reference_files([
        pb.Reference(sensor=1, blob="blobs/ab", filename="photo.png", mask_blob="blobs/cd",
                     mask_filename="mask.png", alpha_mask=True)])
    assert refs[0].on_server and (refs[0].mask, refs[0].alpha_mask) == ("blobs/cd", True)
    client = SimpleNamespace()  # no blobs service: an upload would fail
    again = workflow.upload_references(client, refs)
    assert (again[0].sensor, again[0].blob, again[0].mask_blob, again[0].alpha_mask,
            again[0].mask_filename) == (1, "blobs/ab", "blobs/cd", True, "mask.png")
    with pytest.raises(workflow.MissingFile, match=f"mask '{tmp_path}/m.png' is not a file"):
        workflow.check_reference_files([workflow.ReferenceFile("blobs/ab",
                                                               mask=str(tmp_path / "m.png"))])


class FakeClient:
    """What ``job start`` and ``job status`` touch of a client, answering from memory."""

    def __init__(self, job: pb.Job | None = None) -> None:
        self.info = INFO
        self.jobs = SimpleNamespace(GetJob=lambda request: job)


def cli_spec(monkeypatch, *args: str) -> tuple[pb.JobSpec, str]:
    """The JobSpec ``matopt job start`` creates from ``args``, and its output."""
    created = []

    def start_job(client, spec, refs, initial_from=None, on_upload=None, timeout=None):
        spec.references.extend(workflow.upload_references(client, refs))  # blobs: no upload
        created.append(spec)
        return pb.Job(name="jobs/x")

    monkeypatch.setattr(cli_job, "connected", lambda: FakeClient())
    monkeypatch.setattr(workflow, "start_job", start_job)
    out = CliRunner().invoke(cli, ["job", "start", "scenes/s", "--ref", "blobs/r",
                                   "--param", "k", *args])
    return (created[0] if created else None), out.output


def test_cli_and_qt_build_the_same_spec_from_the_same_settings(monkeypatch, request):
    pytest.importorskip("PySide6.QtWidgets", reason="PySide6 is not installed")
    pytest.importorskip("pytestqt", reason="pytest-qt is not installed")
    from matopt_client.qt import pyside_check
    if pyside_check.none_refcount_bug():
        pytest.skip(pyside_check.problem() or "broken PySide6")
    from matopt_client.qt.job_settings import JobSettingsForm

    qtbot = request.getfixturevalue("qtbot")

    spec, _ = cli_spec(monkeypatch, "--loss", "DUAL_BUFFER", "--schedule", "constant",
                       "--sensor-mode", "step_per_sensor", "--iterations", "7", "--spp", "3",
                       "--min-error", "0.01")
    form = JobSettingsForm()
    qtbot.addWidget(form)
    form.set_choices(workflow.choices(INFO))
    assert [form.loss.itemData(i) for i in range(form.loss.count())] == [None, *INFO.losses]
    form.set_values(loss="dual_buffer", schedule="constant", sensor_mode="step per sensor",
                    iterations=7, spp=3, min_error=0.01, clamp=False)
    qt = workflow.build_spec("scenes/s", [pb.ParameterSpec(key="k")], form.values())
    qt.references.extend(workflow.upload_references(None, [workflow.ReferenceFile("blobs/r")]))
    assert spec == qt and spec.loss == pb.LOSS_DUAL_BUFFER and spec.spp == 3

    # Neither client holds defaults of its own: what is left alone is not sent.
    untouched, _ = cli_spec(monkeypatch)
    fresh = JobSettingsForm()
    qtbot.addWidget(fresh)
    fresh.set_choices(workflow.choices(INFO))
    assert fresh.iterations.text() == fresh.spp.text() == "daemon default"
    qt = workflow.build_spec("scenes/s", [pb.ParameterSpec(key="k")], fresh.values())
    qt.references.extend(workflow.upload_references(None, [workflow.ReferenceFile("blobs/r")]))
    assert untouched == qt
    assert not any(qt.HasField(f) for f in ("iterations", "spp", "min_error", "learning_rate"))
    assert (qt.loss, qt.schedule, qt.sensor_mode) == (0, 0, 0)


def test_cli_refuses_a_loss_the_daemon_does_not_offer(monkeypatch):
    spec, output = cli_spec(monkeypatch, "--loss", "mean_bias_error")
    assert spec is None
    assert "--loss" in output and "unknown loss 'mean_bias_error'" in output
    assert "newer_loss" in output  # the daemon's list, not a copy in the client


def running(iteration: int, total: int = 10, best: int = -1, name: str = "jobs/x") -> pb.Job:
    return pb.Job(name=name, state=pb.JOB_STATE_RUNNING, iteration=iteration,
                  spec=pb.JobSpec(iterations=total), loss=0.5, best_iteration=best,
                  best_loss=0.25, elapsed_seconds=1.5)


def test_job_status_prints_sensor_indices(monkeypatch):
    job = running(3)
    job.sensors_rendered.extend([0])
    monkeypatch.setattr(cli_job, "connected", lambda: FakeClient(job))
    out = CliRunner().invoke(cli, ["job", "status", "jobs/x"]).output
    assert re.search(r"^sensors rendered: +#0$", out, re.MULTILINE), out
    assert "sensors:" not in out


def test_job_watch_prints_the_job_again_only_when_its_state_changes(monkeypatch):
    done = running(2, total=2, best=1)
    done.state = pb.JOB_STATE_SUCCEEDED
    events = [pb.JobEvent(job=running(0, total=2)),
              pb.JobEvent(iteration=pb.IterationRecord(iteration=0, loss=0.5)),
              pb.JobEvent(job=running(1, total=2, best=0)),  # after a batch: its best
              pb.JobEvent(iteration=pb.IterationRecord(iteration=1, loss=0.25)),
              pb.JobEvent(job=done)]

    def follow(client, name, on_event):
        for event in events:
            on_event(event)
        return done

    monkeypatch.setattr(cli_job, "connected", lambda: FakeClient())
    monkeypatch.setattr(cli_job, "follow", follow)
    out = CliRunner().invoke(cli, ["job", "watch", "jobs/x"]).stdout.splitlines()
    assert out[0].startswith("jobs/x RUNNING 0/2")
    assert [line.split(" loss")[0] for line in out[1:3]] == ["iteration 0/2", "iteration 1/2"]
    assert out[3].startswith("jobs/x SUCCEEDED 2/2") and "best 0.25 at iteration 1" in out[3]
    assert len(out) == 4
