"""matopt-qt against real daemons: the thesis workflow, job control, other clients' jobs, and a
daemon that goes away mid-job. The window runs offscreen; the tests call what the toolbar
buttons call (past their file dialogs) and assert what the user would see.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np
import pytest

pytest.importorskip("PySide6.QtWidgets", reason="PySide6 is not installed (pip install matopt-mitsuba[qt])")
pytest.importorskip("pytestqt", reason="pytest-qt is not installed")

from matopt_client.qt import pyside_check  # noqa: E402

if pyside_check.none_refcount_bug():
    pytest.skip(pyside_check.problem() or "broken PySide6", allow_module_level=True)

from PySide6.QtCore import QSettings, QTimer  # noqa: E402

from matopt_client import client as mc  # noqa: E402
from matopt_client.qt.app import MainWindow  # noqa: E402
from matopt_client.qt.connection import ConnectionSettings, SettingsStore  # noqa: E402
from matopt_client.qt.jobs_list import JobsList  # noqa: E402
from matopt_client.qt.params_table import CURRENT, LR, VALUE  # noqa: E402
from matopt_client.qt.scene_control import parse_overrides  # noqa: E402
from matopt_api import __version__  # noqa: E402
from matopt_api.v1 import matopt_pb2 as pb  # noqa: E402

from conftest import TOKENS, Daemon, token_file  # noqa: E402
from scenes import PRINCIPLED, png  # noqa: E402

WALLS = ["red.reflectance.value", "green.reflectance.value", "white.reflectance.value"]
LIGHT = "light.emitter.radiance.value"
BASE_COLOR, ROUGHNESS = "shape_2.bsdf.base_color.value", "shape_2.bsdf.roughness.value"
SECOND_SENSOR = """    <sensor type="perspective" id="side">
        <float name="fov" value="30"/>
        <transform name="to_world"><lookat origin="3, 0.6, 2" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="$resx"/><integer name="height" value="$resy"/>
            <rfilter type="box"/></film>
    </sensor>
"""
TWO_CAMERAS = PRINCIPLED.replace('    <emitter type="constant">', SECOND_SENSOR
                                 + '    <emitter type="constant">', 1)


def make_window(qtbot, tmp_path: Path, **intervals) -> MainWindow:
    store = SettingsStore(QSettings(str(tmp_path / "settings.ini"), QSettings.Format.IniFormat))
    timing = dict(probe_interval_s=0.5, retry_interval_s=0.3, jobs_refresh_s=0.5,
                  preview_interval_s=0.3)
    timing.update(intervals)
    window = MainWindow(store, tmp_path / "cache", **timing)
    qtbot.addWidget(window)
    window.resize(1440, 860)
    window.show()
    return window


def connect(qtbot, window: MainWindow, address: str, token: str | None = None) -> None:
    window.connect_to(ConnectionSettings(address, token))
    qtbot.waitUntil(lambda: window.connection.usable, timeout=15000)


def wait_state(qtbot, window: MainWindow, stubs, state: int, timeout_s: float = 30) -> None:
    """Waits for the window to show the job in ``state``; a timeout says what the daemon and
    the window knew then."""
    try:
        qtbot.waitUntil(lambda: window.job.state == state, timeout=int(timeout_s * 1000))
    except Exception as exc:
        daemon_job = stubs.jobs.GetJob(pb.GetJobRequest(name=window.job.name))
        raise AssertionError(
            f"the window shows {pb.JobState.Name(window.job.state)} after {timeout_s:g} s, "
            f"the daemon {pb.JobState.Name(daemon_job.state)} (notes {list(daemon_job.notes)}); "
            f"calls under way {window.tasks.pending()}; watching: {window._watcher is not None}; "
            f"banner {window.banner.label.text()!r}") from exc


def idle(qtbot, window: MainWindow) -> None:
    try:
        qtbot.waitUntil(lambda: window.tasks.busy() == 0, timeout=30000)
    except Exception as exc:
        raise AssertionError(f"calls still under way after 30 s: {window.tasks.pending()}; "
                             f"{threading.active_count()} threads; process CPU "
                             f"{os.times()[:2]}") from exc


@pytest.fixture
def window(qtbot, daemon, tmp_path) -> MainWindow:
    w = make_window(qtbot, tmp_path)
    connect(qtbot, w, daemon.address)
    yield w
    w.shutdown()


def download(stubs, blob: str, path: Path) -> Path:
    path.write_bytes(b"".join(r.chunk for r in stubs.blobs.DownloadBlob(
        pb.DownloadBlobRequest(name=blob))))
    return path


def cornell_reference(window: MainWindow, stubs, path: Path) -> Path:
    image = stubs.scenes.RenderScene(pb.RenderSceneRequest(
        name=window.scene.name, spp=32)).images[0]
    return download(stubs, image.png_blob, path)


def test_a_late_control_reply_does_not_undo_a_newer_state(window):
    """ResumeJob answers QUEUED; when the worker runs the job before that reply reaches the
    GUI thread, the stream has already shown RUNNING, and the window keeps RUNNING."""
    running = pb.Job(name="jobs/x", state=pb.JOB_STATE_RUNNING)
    running.update_time.FromNanoseconds(2_000)
    queued = pb.Job(name="jobs/x", state=pb.JOB_STATE_QUEUED)
    queued.update_time.FromNanoseconds(1_000)
    window._job_changed(running)
    window._job_changed(queued)
    assert window.job.state == pb.JOB_STATE_RUNNING
    assert window.view.resume_button.isEnabled() is False
    paused = pb.Job(name="jobs/x", state=pb.JOB_STATE_PAUSED)
    paused.update_time.FromNanoseconds(3_000)
    window._job_changed(paused)
    assert window.job.state == pb.JOB_STATE_PAUSED and window.view.resume_button.isEnabled()


def test_workflow_scene_file_to_results_export_and_restart(window, qtbot, stubs, tmp_path,
                                                            monkeypatch):
    scene_dir = tmp_path / "scene"
    scene_dir.mkdir()
    (scene_dir / "two_cameras.xml").write_text(TWO_CAMERAS)
    window.overrides.setText("resx=32 resy=32")
    window.open_scene(scene_dir / "two_cameras.xml")  # what Open scene… does past its dialog
    qtbot.waitUntil(lambda: window.scene is not None, timeout=30000)
    scene = window.scene
    assert [(s.width, s.height) for s in scene.sensors] == [(32, 32), (32, 32)]
    assert "two_cameras.xml" in window.scene_label.text()
    row = window.params.row_of(BASE_COLOR)
    assert window.params.table.item(row, VALUE).text() == "0.41, 0.82, 0.99"
    assert window.params.table.item(row, 2).text() == "rgb"
    assert window.references.list.count() == 2
    # The scene as loaded is previewed at once.
    qtbot.waitUntil(lambda: window.view.render.has_image(), timeout=30000)

    # Reference images of the truth (orange, rougher), one per camera.
    truth = [pb.ParameterValue(key=BASE_COLOR, value=[0.9, 0.35, 0.1]),
             pb.ParameterValue(key=ROUGHNESS, value=[0.6])]
    images = stubs.scenes.RenderScene(pb.RenderSceneRequest(
        name=scene.name, spp=64, parameters=truth)).images
    refs = [download(stubs, i.png_blob, tmp_path / f"ref_cam{i.sensor}.png") for i in images]

    # A wrong number of images is refused at once, naming both numbers.
    assert window.set_reference_files(refs[:1]) is not None
    assert "1 reference image chosen, but the scene has 2 sensors" in window.banner.text()
    # Name order, not selection order, maps images to sensors.
    assert window.set_reference_files([refs[1], refs[0]]) is None
    assert window.banner.text() == ""
    assert [r.filename for r in window.references.references()] == ["ref_cam0.png",
                                                                    "ref_cam1.png"]

    # Starting without a parameter, or with a malformed value, says what is wrong.
    window.start_job()
    assert "select at least one parameter" in window.banner.text()
    window.params.set_checked(BASE_COLOR)
    window.params.set_checked(ROUGHNESS)
    window.params.set_cell(BASE_COLOR, VALUE, "0.5, 0.5")
    window.start_job()
    assert BASE_COLOR in window.banner.text() and "expected 3" in window.banner.text()
    window.params.set_cell(BASE_COLOR, VALUE, "0.5, 0.5, 0.5")
    window.params.set_cell(ROUGHNESS, LR, "0.05")
    window.settings.set_values(loss="mse", iterations=12, spp=4, min_error=0)
    window.start_job()
    qtbot.waitUntil(lambda: window.job is not None, timeout=30000)
    first = window.job.name
    spec = stubs.jobs.GetJob(pb.GetJobRequest(name=first)).spec
    by_key = {p.key: p for p in spec.parameters}
    assert list(by_key[BASE_COLOR].initial_value) == [0.5, 0.5, 0.5]
    assert by_key[ROUGHNESS].learning_rate == pytest.approx(0.05)
    assert list(by_key[ROUGHNESS].initial_value) == []  # unedited: the scene's value
    assert [(r.sensor, r.filename) for r in spec.references] == [(0, "ref_cam0.png"),
                                                                  (1, "ref_cam1.png")]
    assert (spec.loss, spec.iterations, spec.spp, spec.min_error) == (pb.LOSS_MSE, 12, 4, 0)

    qtbot.waitUntil(lambda: window.job.state == pb.JOB_STATE_SUCCEEDED, timeout=60000)
    qtbot.waitUntil(lambda: window.result is not None, timeout=30000)
    idle(qtbot, window)
    assert sorted(window.view.plot.points) == list(range(12))
    seconds = [window.view.plot.points[i][0] for i in range(12)]
    assert seconds == sorted(seconds) and seconds[0] > 0
    assert window.view.progress.value() == window.view.progress.maximum() == 12
    assert "SUCCEEDED" in window.view.header.text()
    assert window.view.result_label.text().startswith("best: iteration ")
    assert window.view.reference.has_image() and window.view.render.has_image()
    assert window.view.render.caption.text().startswith("optimized, best iteration")
    assert first.rsplit("/", 1)[-1] in [n.rsplit("/", 1)[-1] for n in window.jobs.names()]
    assert window.export_action.isEnabled()

    # Last iteration instead of best; the other camera.
    window.set_which("last")
    qtbot.waitUntil(lambda: window.result.which == pb.WHICH_LAST, timeout=30000)
    assert window.result.iteration == 11
    window.set_sensor(1)
    optimized = {i.sensor: i.png_blob for i in window.result.images if i.role == "optimized"}
    qtbot.waitUntil(lambda: window.view.render.key == optimized[1], timeout=30000)
    assert window.view.render.caption.text() == "optimized, last iteration 11"
    current = window.params.table.item(window.params.row_of(BASE_COLOR), CURRENT).text()
    assert len(current.split(",")) == 3 and current != "0.5, 0.5, 0.5"

    # Export: the files of 'matopt job export --which last'.
    window.export_to(tmp_path / "export")
    qtbot.waitUntil(lambda: "exported" in window.banner.text(), timeout=30000)
    written = {p.name for p in (tmp_path / "export").iterdir()}
    assert {"parameters.json", "history.csv", "sensor0_optimized.png", "sensor1_reference.png",
            "sensor1_initial.exr"} <= written
    document = json.loads((tmp_path / "export" / "parameters.json").read_text())
    assert document["which"] == "last" and document["iteration"] == 11

    # Restart with edits: the scene and the references are on the server already.
    uploads = []
    monkeypatch.setattr(mc, "upload_files", lambda *a, **k: uploads.append(a) or [])
    monkeypatch.setattr(mc, "upload_bundle", lambda *a, **k: uploads.append(a))
    window.settings.set_values(loss="dual_buffer", iterations=5)
    window.restart_job()
    qtbot.waitUntil(lambda: window.job is not None and window.job.name != first, timeout=30000)
    again = stubs.jobs.GetJob(pb.GetJobRequest(name=window.job.name)).spec
    assert uploads == []
    assert again.scene == spec.scene
    assert [r.blob for r in again.references] == [r.blob for r in spec.references]
    assert (again.loss, again.iterations) == (pb.LOSS_DUAL_BUFFER, 5)
    assert {p.key: list(p.initial_value) for p in again.parameters}[BASE_COLOR] == [0.5] * 3
    qtbot.waitUntil(lambda: window.job.state == pb.JOB_STATE_SUCCEEDED, timeout=60000)
    qtbot.waitUntil(lambda: window.result is not None, timeout=30000)

    # Continue from the result: its values become the start values of the next job.
    window.view.use_result_button.click()
    result = {v.key: v.value for v in window.result.parameters}
    cell = window.params.table.item(window.params.row_of(BASE_COLOR), VALUE).text()
    assert [float(x) for x in cell.split(",")] == pytest.approx(list(result[BASE_COLOR]),
                                                                abs=1e-6)
    specs = {spec.key: list(spec.initial_value) for spec in window.params.specs()}
    assert specs[BASE_COLOR] == pytest.approx(list(result[BASE_COLOR]), abs=1e-6)
    assert window.continue_label.text().startswith(f"Continues from {window.job.name} (last)")
    previous = window.job.name
    window.settings.set_values(iterations=2)
    window.start_job()
    qtbot.waitUntil(lambda: window.job.name != previous, timeout=30000)
    started = {p.key: list(p.initial_value) for p in stubs.jobs.GetJob(
        pb.GetJobRequest(name=window.job.name)).spec.parameters}
    assert started[BASE_COLOR] == pytest.approx(list(result[BASE_COLOR]), abs=1e-6)
    assert started[ROUGHNESS] == pytest.approx(list(result[ROUGHNESS]), abs=1e-6)
    assert window.continue_label.isHidden()
    qtbot.waitUntil(lambda: window.job.state == pb.JOB_STATE_SUCCEEDED, timeout=60000)
    idle(qtbot, window)


def test_job_from_another_client_is_listed_opened_and_watched(window, qtbot, stubs):
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "32",
                                                                      "resy": "32"}))
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=16)).images[0]
    truth = [pb.ParameterValue(key=p.key, value=p.value) for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name)).parameters if p.key in WALLS]
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=25, min_error=0, seed=7, loss=pb.LOSS_MAE,
        sensor_mode=pb.SENSOR_MODE_STEP_PER_SENSOR, clamp=True, ground_truth=truth,
        references=[pb.Reference(blob=ref.exr_blob, filename="cli-ref.exr")],
        parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3) for k in WALLS])))
    qtbot.waitUntil(lambda: job.name in window.jobs.names(), timeout=15000)  # periodic refresh
    window.jobs.select(job.name)
    window.jobs.open_button.click()
    qtbot.waitUntil(lambda: window.job is not None and window.job.name == job.name,
                    timeout=15000)
    # Its scene and spec are in the setup, ready to be edited and restarted.
    assert window.scene.name == scene.name
    assert sorted(window.params.checked_keys()) == sorted(WALLS)
    assert [r.filename for r in window.references.references()] == ["cli-ref.exr"]
    assert window.references.references()[0].on_server
    settings = window.settings
    assert (settings.loss.currentText(), settings.sensor_mode.currentText(),
            settings.clamp.isChecked()) == ("mae", "step per sensor", True)
    assert "seed 7" in window.kept_label.text()
    qtbot.waitUntil(lambda: window.job.state == pb.JOB_STATE_SUCCEEDED, timeout=60000)
    qtbot.waitUntil(lambda: sorted(window.view.plot.points) == list(range(25)), timeout=15000)
    # The latest iteration's error of each wall against the truth, as 'matopt job history'.
    qtbot.waitUntil(lambda: "iteration 24:" in window.view.truth_errors.text(), timeout=15000)
    shown = window.view.truth_errors.text().splitlines()[1:]
    assert sorted(line.split(":")[0].strip() for line in shown) == sorted(WALLS)
    assert all("rmse " in line and " dB" in line for line in shown), shown
    assert window.view.truth_errors.isVisible() and window.view.gains.isHidden()
    # With ground truth, each wall's relative error is plotted against time beside the loss,
    # falling from the grey start (the plot draws it: the legend names both walls).
    errors = window.view.plot.error_points()
    assert sorted(errors) == sorted(WALLS) and all(len(errors[k]) == 25 for k in WALLS)
    assert all(errors[k][-1][1] < errors[k][0][1] for k in WALLS)
    window.view.plot.grab()
    # The daemon's PNG of the EXR reference appears with the results.
    qtbot.waitUntil(lambda: window.view.reference.has_image(), timeout=15000)
    assert window.view.reference.caption.text().startswith("sensor 0")
    window.view.role.setCurrentText("error")
    qtbot.waitUntil(lambda: window.view.render.caption.text().startswith(
        "|optimized − reference|, best iteration"), timeout=15000)

    # Restarted with one edit, the new job keeps everything else of the old spec, including
    # what the window has no field for (the seed).
    settings.set_values(iterations=3)
    window.restart_job()
    qtbot.waitUntil(lambda: window.job.name != job.name, timeout=15000)
    spec = stubs.jobs.GetJob(pb.GetJobRequest(name=window.job.name)).spec
    assert (spec.iterations, spec.seed, spec.loss, spec.sensor_mode, spec.clamp) == (
        3, 7, pb.LOSS_MAE, pb.SENSOR_MODE_STEP_PER_SENSOR, True)
    assert [r.blob for r in spec.references] == [ref.exr_blob]
    assert {p.key: list(p.initial_value) for p in spec.parameters} == {k: [0.5] * 3
                                                                        for k in WALLS}
    qtbot.waitUntil(lambda: window.job.state == pb.JOB_STATE_SUCCEEDED, timeout=60000)
    idle(qtbot, window)


def test_photograph_with_a_mask_and_an_unknown_exposure(window, qtbot, stubs, tmp_path):
    """A "photograph" of the Cornell box taken at another exposure and white balance (the
    light scaled by a tint: the image scales with it), with a mask over a fixture. The mask
    chosen in the window reaches the job, and with Fit exposure ticked the result shows the
    gains, near the tint."""
    tint = [0.6, 0.5, 0.4]
    window.open_cornell_box({"resx": "32", "resy": "32"})
    qtbot.waitUntil(lambda: window.scene is not None, timeout=30000)
    light = next(p for p in window.parameters if p.key == LIGHT)
    dim = pb.ParameterValue(key=LIGHT, value=[v * t for v, t in zip(light.value, tint)])
    image = stubs.scenes.RenderScene(pb.RenderSceneRequest(
        name=window.scene.name, spp=64, parameters=[dim])).images[0]
    photo = download(stubs, image.exr_blob, tmp_path / "dim.exr")
    mask = np.ones((32, 32))
    mask[20:, 10:22] = 0.0
    (tmp_path / "dim_mask.png").write_bytes(png(mask))
    assert window.set_reference_files([photo]) is None

    # Mask ▸ Mask image… (past its dialog) and Mask ▸ Its alpha channel, on the selected row.
    refs = window.references
    refs.list.setCurrentRow(0)
    assert refs.mask_button.isEnabled()
    assert refs.set_mask(0, str(tmp_path / "dim_mask.png")) is None
    refs.alpha_action.trigger()
    assert "dim.exr (mask dim_mask.png, its alpha)" in refs.list.item(0).text()
    refs.alpha_action.trigger()  # an EXR without alpha: the daemon would refuse it
    assert refs.list.item(0).text().endswith("dim.exr (mask dim_mask.png)")

    # The red wall from the scene's value, the light as it is: the gain is identifiable.
    window.params.set_checked(WALLS[0])
    window.settings.set_values(iterations=8, spp=16, min_error=0, fit_exposure=True)
    window.start_job()
    qtbot.waitUntil(lambda: window.job is not None, timeout=30000)
    spec = stubs.jobs.GetJob(pb.GetJobRequest(name=window.job.name)).spec
    [reference] = spec.references
    assert reference.mask_blob.startswith("blobs/") and reference.mask_filename == "dim_mask.png"
    assert not reference.alpha_mask and spec.fit_exposure
    assert "(mask dim_mask.png) — on server" in refs.list.item(0).text()

    qtbot.waitUntil(lambda: window.job.state == pb.JOB_STATE_SUCCEEDED, timeout=60000)
    qtbot.waitUntil(lambda: window.result is not None, timeout=30000)
    idle(qtbot, window)
    assert f"mask 'dim_mask.png' leaves out {int((mask == 0).sum())} of 1024" \
        in window.view.notes.text()
    heading, line = window.view.gains.text().splitlines()
    assert heading == f"Fitted exposure, best iteration {window.result.iteration}:"
    label, values = line.strip().split(": ")
    assert label == "gain of dim.exr"
    # each channel "value +- standard error"
    assert [float(v.split("+-")[0]) for v in values.split(",")] == pytest.approx(tint, rel=0.05)
    assert window.view.truth_errors.isHidden()  # no ground truth

    # Opened again (e.g. to restart), the job brings its Fit exposure along.
    window.settings.set_values(fit_exposure=False)
    window.open_job(window.job.name)
    qtbot.waitUntil(lambda: window.settings.fit_exposure.isChecked(), timeout=15000)
    idle(qtbot, window)


def test_pause_resume_cancel_with_live_preview(window, qtbot, stubs, tmp_path):
    window.open_cornell_box({"resx": "32", "resy": "32"})
    qtbot.waitUntil(lambda: window.scene is not None, timeout=30000)
    assert window.scene.display_name == "cornell-box"
    assert window.set_reference_files([cornell_reference(window, stubs,
                                                         tmp_path / "ref.png")]) is None
    for key in WALLS:
        window.params.set_checked(key)
        window.params.set_cell(key, VALUE, "0.5, 0.5, 0.5")
    window.settings.set_values(iterations=100000, min_error=0, spp=1)
    window.start_job()
    qtbot.waitUntil(lambda: window.job is not None and window.latest is not None
                    and window.latest.iteration >= 3, timeout=30000)
    name = window.job.name
    # While it runs, the latest iterate is rendered every so often.
    qtbot.waitUntil(lambda: window.view.render.caption.text().startswith("preview of iteration"),
                    timeout=30000)
    assert window.view.reference.has_image()
    assert window.view.pause_button.isEnabled() and not window.view.resume_button.isEnabled()

    assert not window.view.estimate_button.isEnabled()
    window.pause_job()
    wait_state(qtbot, window, stubs, pb.JOB_STATE_PAUSED)
    assert window.view.resume_button.isEnabled() and not window.view.pause_button.isEnabled()
    # Paused, how sure is each wall colour? The table shows each value's verdict: +- its
    # standard error, or not determined (a wall a short, noisy job has not settled yet).
    window.view.estimate_button.click()
    qtbot.waitUntil(lambda: all(
        any(v in window.params.table.item(window.params.row_of(k), CURRENT).text()
            for v in ("+-", "not determined")) for k in WALLS), timeout=120000)
    assert "standard errors: 9 components" in window.view.result_label.toolTip()
    window.resume_job()
    wait_state(qtbot, window, stubs, pb.JOB_STATE_RUNNING)
    window.view.cancel_button.click()
    # The end phase (result renders) waits for a worker turn in the shared daemon, where the
    # suite's other users may still have jobs queued.
    wait_state(qtbot, window, stubs, pb.JOB_STATE_CANCELLED, 120)
    assert stubs.jobs.GetJob(pb.GetJobRequest(name=name)).state == pb.JOB_STATE_CANCELLED
    # A cancelled job keeps its results so far.
    qtbot.waitUntil(lambda: window.result is not None, timeout=30000)
    assert "CANCELLED" in window.view.header.text()
    assert not any(b.isEnabled() for b in (window.view.pause_button, window.view.resume_button,
                                           window.view.cancel_button))
    assert window.banner.level != "error"
    idle(qtbot, window)


def test_a_watched_job_rewrites_its_own_row_of_a_long_list(qtbot):
    """A running job sends several events a second, each a new state of its row; the list
    of all the user's jobs must not be rebuilt for each (a full rebuild of 300 rows, with
    columns sized to their contents on every cell, took 19 s and froze the window)."""
    jobs_list = JobsList()
    qtbot.addWidget(jobs_list)
    jobs = []
    for i in range(300):
        job = pb.Job(name=f"jobs/{i:012x}", state=pb.JOB_STATE_SUCCEEDED, iteration=100)
        job.spec.iterations = 100
        job.create_time.FromSeconds(1_795_464_000 + i)
        jobs.append(job)
    running = jobs[7]
    running.state, running.iteration = pb.JOB_STATE_RUNNING, 3
    jobs_list.set_jobs(jobs)
    jobs_list.set_current(running.name)
    row = jobs_list.names().index(running.name)
    before = [[jobs_list.table.item(r, c) for c in range(5)] for r in range(300)]

    newer = pb.Job()
    newer.CopyFrom(running)
    newer.iteration = 40
    jobs_list.update_job(newer)
    assert jobs_list.table.item(row, 2).text() == "40/100"
    assert jobs_list.table.item(row, 0).font().bold()
    jobs_list.set_jobs(jobs_list.jobs)  # a refresh with nothing new
    after = [[jobs_list.table.item(r, c) for c in range(5)] for r in range(300)]
    assert all(a is b for ra, rb in zip(before, after) for a, b in zip(ra, rb))
    assert jobs_list.table.horizontalHeader().sectionResizeMode(0) \
        != jobs_list.table.horizontalHeader().ResizeMode.ResizeToContents


def test_daemon_going_away_mid_job(qtbot, tmp_path, caplog, capfd):
    caplog.set_level("DEBUG")
    tokens = token_file(tmp_path)
    data = tmp_path / "data"
    daemon = Daemon(data, tokens).start()
    window = make_window(qtbot, tmp_path)
    token = TOKENS["alice"]
    try:
        connect(qtbot, window, daemon.address, token)
        assert window.connection.info.user == "alice"
        window.open_cornell_box({"resx": "32", "resy": "32"})
        qtbot.waitUntil(lambda: window.scene is not None, timeout=30000)
        stubs = mc.connect(daemon.address, token)
        ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=window.scene.name,
                                                             spp=16)).images[0]
        window.set_reference_files([mc.download_blob(stubs, ref.png_blob, tmp_path / "r.png")])
        stubs.close()
        for key in WALLS:
            window.params.set_checked(key)
        window.settings.set_values(iterations=100000, min_error=0, spp=1)
        window.start_job()
        qtbot.waitUntil(lambda: window.latest is not None and window.latest.iteration >= 3,
                        timeout=30000)
        name = window.job.name

        daemon.proc.send_signal(signal.SIGTERM)  # not daemon.stop(): the GUI loop keeps going
        address = daemon.address
        qtbot.waitUntil(lambda: f"lost connection to matoptd at {address}: UNAVAILABLE"
                        in window.banner.text(), timeout=30000)
        assert window.banner.level == "error"
        # Wait with the GUI's event loop running (proc.wait() would block it here, not the app).
        qtbot.waitUntil(lambda: daemon.proc.poll() is not None, timeout=60000)

        # Responsive while the daemon is gone: timers fire on time, the table filters.
        ticks = []
        timer = QTimer()
        timer.timeout.connect(lambda: ticks.append(time.monotonic()))
        timer.start(20)
        qtbot.wait(1000)
        timer.stop()
        assert len(ticks) >= 25 and max(b - a for a, b in zip(ticks, ticks[1:])) < 0.5
        window.params.filter.setText("red")
        assert [window.params.table.isRowHidden(i) for i in range(len(window.params.rows))
                ].count(False) == 1
        window.params.filter.setText("")
        assert "retrying" in window.banner.text()

        # The daemon comes back on the same address: the window reconnects by itself and
        # shows the job as the daemon left it; Resume continues it.
        back = Daemon(data, tokens, "--listen", address).start()
        try:
            qtbot.waitUntil(lambda: window.connection.usable and window.banner.level != "error",
                            timeout=30000)
            qtbot.waitUntil(lambda: window.job.state == pb.JOB_STATE_INTERRUPTED, timeout=30000)
            assert window.view.resume_button.isEnabled()
            window.resume_job()
            qtbot.waitUntil(lambda: window.job.state == pb.JOB_STATE_RUNNING, timeout=30000)
            window.cancel_job()
            qtbot.waitUntil(lambda: window.job.state == pb.JOB_STATE_CANCELLED, timeout=30000)
            assert window.job.name == name
            idle(qtbot, window)
        finally:
            window.shutdown()
            back.stop()
    finally:
        window.shutdown()
        daemon.stop()

    # The settings come back in the next session; the token was never printed or logged.
    saved = SettingsStore(QSettings(str(tmp_path / "settings.ini"),
                                    QSettings.Format.IniFormat)).load_connection()
    assert (saved.server, saved.token) == (address, token)
    assert token not in repr(saved)
    out, err = capfd.readouterr()
    assert token not in out + err + caplog.text
    assert "lost connection" in caplog.text


def test_refused_token_is_reported_not_retried(qtbot, tmp_path):
    tokens = tmp_path / "tokens"
    tokens.write_text(f"{TOKENS['alice']} alice\n")
    daemon = Daemon(tmp_path / "data", tokens).start()
    window = make_window(qtbot, tmp_path)
    try:
        window.connect_to(ConnectionSettings(daemon.address, "not-a-token-0123456789"))
        qtbot.waitUntil(lambda: "UNAUTHENTICATED" in window.banner.text(), timeout=15000)
        assert f"cannot connect to matoptd at {daemon.address}" in window.banner.text()
        assert "not-a-token" not in window.banner.text()
        assert not window.open_action.isEnabled()
    finally:
        window.shutdown()
        daemon.stop()


def test_unreachable_server_at_start_is_a_banner_and_the_window_works(qtbot, tmp_path):
    window = make_window(qtbot, tmp_path)
    window.connect_to(ConnectionSettings("127.0.0.1:1"))
    qtbot.waitUntil(lambda: "cannot reach matoptd at 127.0.0.1:1" in window.banner.text(),
                    timeout=15000)
    window.start_job()  # nothing loaded: says so instead of failing
    assert window.banner.text()
    window.shutdown()


def test_server_that_never_answers_keeps_the_window_responsive(qtbot, tmp_path):
    # A listener that accepts connections and then says nothing: a hung daemon.
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    address = f"127.0.0.1:{listener.getsockname()[1]}"
    window = make_window(qtbot, tmp_path)
    try:
        ticks = []
        timer = QTimer()
        timer.timeout.connect(lambda: ticks.append(time.monotonic()))
        timer.start(20)
        started = time.monotonic()
        window.connect_to(ConnectionSettings(address))
        assert time.monotonic() - started < 0.5  # connect_to does not wait for the daemon
        qtbot.waitUntil(lambda: f"cannot reach matoptd at {address}" in window.banner.text(),
                        timeout=20000)
        timer.stop()
        assert "no answer within" in window.banner.text()
        assert max(b - a for a, b in zip(ticks, ticks[1:])) < 0.5
    finally:
        window.shutdown()
        listener.close()


def test_settings_are_remembered_and_the_token_is_private(tmp_path):
    path = tmp_path / "settings.ini"
    store = SettingsStore(QSettings(str(path), QSettings.Format.IniFormat))
    store.save_connection(ConnectionSettings("gpu-box:50051", "secret-token-0123456789",
                                             str(tmp_path / "ca.pem")))
    again = SettingsStore(QSettings(str(path), QSettings.Format.IniFormat)).load_connection()
    assert (again.server, again.token, again.tls_ca) == ("gpu-box:50051",
                                                         "secret-token-0123456789",
                                                         str(tmp_path / "ca.pem"))
    assert "secret-token" not in repr(again)
    if os.name == "posix":
        assert path.stat().st_mode & 0o077 == 0
    store.save_connection(ConnectionSettings("gpu-box:50051", "secret-token-0123456789",
                                             remember_token=False))
    assert "secret-token" not in path.read_text()


def test_qt_client_needs_neither_mitsuba_nor_drjit_nor_the_daemon():
    code = ("import sys\n"
            "for m in ('mitsuba', 'drjit', 'matoptd'):\n"
            "    sys.modules[m] = None\n"
            "import matopt_client.qt.app\n"
            "from matopt_client.qt.app import main\n"
            "sys.argv = ['matopt-qt', '--help']\n"
            "main()\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, env=dict(os.environ, QT_QPA_PLATFORM="offscreen"))
    assert out.returncode == 0, out.stderr
    assert "usage: matopt-qt" in out.stdout
    assert "--token" not in out.stdout  # a token on the command line is visible to others


def test_parse_overrides():
    assert parse_overrides("resx=64, resy=64 spp=4") == {"resx": "64", "resy": "64", "spp": "4"}
    with pytest.raises(ValueError, match="'resx' is not of the form NAME=VALUE"):
        parse_overrides("resx")



@pytest.fixture
def x_display():
    """A display of Xvfb's (skipped where it is not installed: deploy/setup.sh installs it
    with the test extra)."""
    if not shutil.which("Xvfb"):
        pytest.skip("needs Xvfb (apt-get install xvfb)")
    read, write = os.pipe()
    xvfb = subprocess.Popen(["Xvfb", "-displayfd", str(write), "-screen", "0", "1280x1024x24",
                             "-nolisten", "tcp"], pass_fds=[write],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(write)
    with os.fdopen(read) as pipe:
        number = pipe.readline().strip()
    try:
        assert number, "Xvfb reported no display"
        yield f":{number}"
    finally:
        xvfb.terminate()
        xvfb.wait(timeout=30)


def test_the_app_starts_on_an_x_server(daemon, x_display, tmp_path):
    """matopt-qt on a plain X server (Qt's xcb platform, not offscreen): it aborted while
    libxcb-cursor0, libxcb-icccm4 and libxcb-keysyms1 were missing. It opens its window and
    connects; a timer started before main() then ends it."""
    code = ("import sys\n"
            "from PySide6.QtCore import QTimer\n"
            "from PySide6.QtWidgets import QApplication\n"
            "from matopt_client.qt.app import MainWindow, main\n"
            "app = QApplication(sys.argv[:1])\n"
            "def check():\n"
            "    window = next(w for w in app.topLevelWidgets() if isinstance(w, MainWindow))\n"
            "    if window.isVisible() and window.connection.info is not None:\n"
            "        print(app.platformName(), window.connection.info.version)\n"
            "        app.quit()\n"
            "timer = QTimer(interval=100, timeout=check)\n"
            "timer.start()\n"
            "QTimer.singleShot(60000, lambda: app.exit(3))\n"
            f"sys.exit(main(['--server', {daemon.address!r}]))\n")
    env = {**os.environ, "DISPLAY": x_display, "QT_QPA_PLATFORM": "xcb",
           "XDG_CONFIG_HOME": str(tmp_path), "HOME": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split() == ["xcb", __version__]  # the window, connected to the daemon
