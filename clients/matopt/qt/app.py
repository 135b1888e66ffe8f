"""The main window: the thesis tool's workflow on top of the matoptd API.

Left, the jobs on the server; in the middle, the setup of the next job (scene, parameter
table, one reference per sensor, loss and iterations); right, the job being shown (progress,
pause/resume/cancel, reference beside render, loss against seconds, best/last, export).

The window owns no rendering and no job: the daemon does. Every call to it runs on a worker
thread (:mod:`matopt.qt.worker`) and comes back as a callback here, so the window keeps
painting, and says so in a banner, when the daemon is slow or gone.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import grpc
from PySide6.QtCore import QByteArray, QStandardPaths, Qt, QTimer, Signal, Slot
from PySide6.QtGui import QAction, QCloseEvent, QKeySequence
from PySide6.QtWidgets import (QApplication, QDockWidget, QFileDialog, QGroupBox, QHBoxLayout,
                               QLabel, QLineEdit, QMainWindow, QPushButton, QSplitter,
                               QToolButton, QVBoxLayout, QWidget)

from matopt import client as mc
from matopt import workflow
from matopt.export import export_job
from matopt.qt import pyside_check
from matopt.qt.banner import Banner
from matopt.qt.connection import (ConnectDialog, Connection, ConnectionSettings, SettingsStore)
from matopt.qt.images import BlobCache, read_image
from matopt.qt.job_settings import JobSettingsForm
from matopt.qt.job_view import JobView
from matopt.qt.jobs_list import JobsList
from matopt.qt.params_table import ParamsTable
from matopt.qt.references import ReferenceList
from matopt.qt.worker import CALL_TIMEOUT_S, JobWatcher, Tasks
from matopt.qt.workers_label import WorkersLabel
from matopt_api.v1 import matopt_pb2 as pb

log = logging.getLogger(__name__)

SCENE_PREVIEW_SPP = 16


def parse_overrides(text: str) -> dict[str, str]:
    """The XML-defaults field: ``"resx=64 resy=64"`` -> {"resx": "64", "resy": "64"}."""
    return workflow.parse_overrides(workflow.split_overrides(text))


def _create_scene(client: mc.Client, path: str | None, overrides: dict[str, str],
                  on_upload: Callable[[str, int], None]
                  ) -> tuple[pb.Scene, list[pb.Parameter]]:
    """Worker thread: creates the scene (``path`` None: the built-in Cornell box) and lists
    its parameters."""
    scene = workflow.create_scene(client, path, overrides, on_upload=on_upload)
    parameters = client.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name), timeout=CALL_TIMEOUT_S).parameters
    return scene, list(parameters)


def _fetch_job(client: mc.Client, name: str, known_scene: str | None
               ) -> tuple[pb.Job, pb.Scene | None, list[pb.Parameter] | None, str]:
    """Worker thread: the job, and its scene and parameters unless the window has them.

    A job whose scene was deleted can still be watched and exported; the last element
    explains why it cannot be restarted.
    """
    job = client.jobs.GetJob(pb.GetJobRequest(name=name), timeout=CALL_TIMEOUT_S)
    if job.spec.scene == known_scene:
        return job, None, None, ""
    try:
        scene = client.scenes.GetScene(pb.GetSceneRequest(name=job.spec.scene),
                                       timeout=CALL_TIMEOUT_S)
        parameters = client.scenes.ListSceneParameters(
            pb.ListSceneParametersRequest(name=scene.name), timeout=CALL_TIMEOUT_S).parameters
    except grpc.RpcError as exc:
        if exc.code() != grpc.StatusCode.NOT_FOUND:
            raise
        return job, None, None, (f"the job's scene {job.spec.scene} no longer exists: the "
                                 f"job can be watched and exported, not restarted")
    return job, scene, list(parameters), ""


class MainWindow(QMainWindow):
    """The app. Its public methods are what the toolbar buttons do, minus the file dialogs,
    so tests (and scripts) drive the same code paths a user does."""

    _upload_note = Signal(str)

    def __init__(self, store: SettingsStore | None = None, cache_dir: str | Path | None = None,
                 *, probe_interval_s: float = 5.0, retry_interval_s: float = 2.0,
                 jobs_refresh_s: float = 5.0, preview_interval_s: float = 5.0,
                 preview_spp: int = 16) -> None:
        super().__init__()
        self.store = store or SettingsStore()
        if cache_dir is None:
            base = QStandardPaths.writableLocation(QStandardPaths.StandardLocation.CacheLocation)
            cache_dir = Path(base or Path.home() / ".cache" / "matopt-qt") / "blobs"
        self.cache = BlobCache(cache_dir)
        self.tasks = Tasks(self)
        self.connection = Connection(self.tasks, probe_interval_s, retry_interval_s, self)
        self.preview_interval_s, self.preview_spp = preview_interval_s, preview_spp

        # What is shown: the setup's scene, and the job on the right (may be another scene's
        # until it is opened, which loads its scene into the setup).
        self.scene: pb.Scene | None = None
        self.parameters: list[pb.Parameter] = []
        self.job: pb.Job | None = None
        # The spec of the job opened or started last: a restart keeps whatever the setup does
        # not show (seed, resolution, ground truth, ...) instead of silently dropping it.
        self.base_spec: pb.JobSpec | None = None
        self.result: pb.JobResult | None = None
        self.latest: pb.IterationRecord | None = None
        self.best_loss: float | None = None
        self.previews: dict[int, tuple[Any, str]] = {}  # sensor -> (QImage, caption)
        self.jobs_loading = False
        self._watcher: JobWatcher | None = None
        self._old_watchers: list[JobWatcher] = []
        self._watch_generation = 0
        self._preview_busy = False
        self._starting = False
        self._shut_down = False
        self._wanted: dict[int, str | None] = {}  # id(pane) -> key of the image it awaits

        self._build()
        self.connection.connected.connect(self._connected)
        self.connection.restored.connect(self._restored)
        self.connection.lost.connect(self._lost)
        self.connection.failed.connect(self._connect_failed)
        # Every GetServerInfo answer (on connecting, then the connection's probe every few
        # seconds) refreshes the workers; a failed probe goes to the lost-connection banner
        # once, like any call, and the label hides until the daemon answers again.
        self.connection.info_received.connect(self.workers_label.set_info)
        self._upload_note.connect(self._show_upload, Qt.ConnectionType.QueuedConnection)

        self.jobs_timer = QTimer(self)
        self.jobs_timer.timeout.connect(self.refresh_jobs)
        self.jobs_timer.start(max(200, int(jobs_refresh_s * 1000)))
        self.preview_timer = QTimer(self)
        self.preview_timer.timeout.connect(self._preview_tick)
        self.preview_timer.start(max(100, int(preview_interval_s * 1000)))
        self._update_actions()
        geometry = self.store.qsettings.value("window/geometry")
        if isinstance(geometry, QByteArray):
            self.restoreGeometry(geometry)

    # =========================================================================================
    # Layout
    # =========================================================================================

    def _build(self) -> None:
        self.setWindowTitle("matopt")
        self.resize(1440, 860)
        toolbar = self.addToolBar("Main")
        toolbar.setObjectName("main-toolbar")
        toolbar.setMovable(False)

        def action(text: str, slot: Callable, shortcut: str | None = None,
                   tip: str = "") -> QAction:
            a = QAction(text, self)
            a.triggered.connect(slot)
            if shortcut:
                a.setShortcut(QKeySequence(shortcut))
            if tip:
                a.setToolTip(tip)
            toolbar.addAction(a)
            return a

        self.connect_action = action("Connect…", self.connect_dialog,
                                     tip="server, token and TLS CA of matoptd")
        toolbar.addSeparator()
        self.open_action = action("Open scene…", self.open_scene_dialog, "Ctrl+O",
                                  "upload a Mitsuba scene XML and every file it references")
        self.cornell_action = action("Cornell box", lambda: self.open_cornell_box(),
                                     tip="the daemon's built-in test scene")
        self.overrides = QLineEdit(self.store.value("scene/overrides"))
        self.overrides.setPlaceholderText("XML defaults, e.g. resx=64 resy=64")
        self.overrides.setToolTip("<default> values a scene is loaded with (as the CLI's "
                                  "--set); applied when a scene is opened")
        self.overrides.setMaximumWidth(220)
        toolbar.addWidget(QLabel(" with "))
        toolbar.addWidget(self.overrides)
        self.references_action = action("Load references…", self._choose_references, "Ctrl+R",
                                        "one reference image per sensor")
        toolbar.addSeparator()
        self.start_action = action("Start", self.start_job, "Ctrl+Return",
                                   "start a job with the setup on the left (a job opened from "
                                   "the list: restart it with your edits)")
        self.pause_action = action("Pause", self.pause_job)
        self.resume_action = action("Resume", self.resume_job)
        self.cancel_action = action("Cancel", self.cancel_job)
        toolbar.addSeparator()
        self.export_action = action("Export…", self.export_dialog, "Ctrl+E",
                                    "write the shown result to a folder")

        central = QWidget()
        outer = QVBoxLayout(central)
        outer.setContentsMargins(6, 4, 6, 4)
        self.banner = Banner()
        outer.addWidget(self.banner)
        splitter = QSplitter(Qt.Orientation.Horizontal)
        outer.addWidget(splitter, 1)
        self.setCentralWidget(central)

        # Setup of the next job.
        setup = QWidget()
        column = QVBoxLayout(setup)
        column.setContentsMargins(0, 0, 4, 0)
        self.scene_label = QLabel("<b>No scene</b> — Open scene… or Cornell box")
        self.scene_label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        column.addWidget(self.scene_label)
        self.params = ParamsTable()
        self.params.changed.connect(self._update_actions)
        column.addWidget(self.params, 1)
        lower = QHBoxLayout()
        refs_box = QGroupBox("References (one per sensor)")
        refs_layout = QVBoxLayout(refs_box)
        self.references = ReferenceList()
        self.references.start_folder = self.store.folder("references")
        self.references.problem.connect(lambda text: self.show_banner(text, "warning"))
        self.references.changed.connect(self._references_changed)
        refs_layout.addWidget(self.references)
        lower.addWidget(refs_box, 3)
        settings_box = QGroupBox("Optimization")
        settings_layout = QVBoxLayout(settings_box)
        self.settings = JobSettingsForm()
        settings_layout.addWidget(self.settings)
        self.kept_label = QLabel("")
        self.kept_label.setWordWrap(True)
        self.kept_label.setStyleSheet("QLabel { color: #555; }")
        self.kept_label.setToolTip("settings of the opened job that this window has no field "
                                   "for; a restart keeps them")
        self.kept_label.hide()
        settings_layout.addWidget(self.kept_label)
        continue_row = QHBoxLayout()
        self.continue_label = QLabel("")
        self.continue_label.setWordWrap(True)
        self.continue_label.setStyleSheet("QLabel { color: #0d3c6e; }")
        self.continue_clear = QToolButton()
        self.continue_clear.setText("✕")
        self.continue_clear.setAutoRaise(True)
        self.continue_clear.setToolTip("start from the table's values and the scene's instead")
        self.continue_clear.clicked.connect(lambda: self._set_initial_from(None))
        continue_row.addWidget(self.continue_label, 1)
        continue_row.addWidget(self.continue_clear)
        settings_layout.addLayout(continue_row)
        self.initial_from: tuple[str, int] | None = None  # (job, pb.Which) to continue from
        self._set_initial_from(None)
        self.start_button = QPushButton("Start")
        self.start_button.setDefault(True)
        self.start_button.clicked.connect(self.start_job)
        settings_layout.addWidget(self.start_button)
        lower.addWidget(settings_box, 2)
        column.addLayout(lower)
        splitter.addWidget(setup)

        # The job being shown.
        self.view = JobView()
        self.view.pause_button.clicked.connect(self.pause_job)
        self.view.resume_button.clicked.connect(self.resume_job)
        self.view.cancel_button.clicked.connect(self.cancel_job)
        self.view.export_button.clicked.connect(self.export_dialog)
        self.view.use_result_button.clicked.connect(self.use_result_as_start)
        self.view.sensor.currentIndexChanged.connect(lambda _: self._sensor_changed())
        self.view.best_radio.toggled.connect(lambda _: self._which_changed())
        self.view.role.currentIndexChanged.connect(lambda _: self._update_images())
        splitter.addWidget(self.view)
        splitter.setStretchFactor(0, 1)
        splitter.setStretchFactor(1, 1)
        splitter.setSizes([600, 560])

        # The user's jobs.
        self.jobs = JobsList()
        self.jobs.open_requested.connect(self.open_job)
        self.jobs.refresh_requested.connect(self.refresh_jobs)
        dock = QDockWidget("Jobs on the server", self)
        dock.setObjectName("jobs-dock")
        dock.setWidget(self.jobs)
        dock.setFeatures(QDockWidget.DockWidgetFeature.DockWidgetMovable
                         | QDockWidget.DockWidgetFeature.DockWidgetFloatable)
        self.addDockWidget(Qt.DockWidgetArea.LeftDockWidgetArea, dock)
        self.resizeDocks([dock], [270], Qt.Orientation.Horizontal)

        self.workers_label = WorkersLabel()
        self.statusBar().addPermanentWidget(self.workers_label)
        self.connection_label = QLabel("not connected")
        self.statusBar().addPermanentWidget(self.connection_label)

    # =========================================================================================
    # Messages
    # =========================================================================================

    def show_banner(self, text: str, level: str = "error") -> None:
        self.banner.show_message(text, level)
        if level != "info":
            log.info("%s", text)

    def status(self, text: str, ms: int = 8000) -> None:
        self.statusBar().showMessage(text, ms)

    def _call(self, what: str, fn: Callable[[mc.Client], Any], on_done: Callable[[Any], None],
              on_error: Callable[[BaseException], None] | None = None,
              quiet_codes: Sequence[grpc.StatusCode] = ()) -> bool:
        """Runs ``fn(client)`` off the GUI thread; a failure becomes a banner.

        ``what`` says what was being done ("starting the job"), so the banner reads as a
        sentence. Connection failures go to the connection, which shows the lost-connection
        banner and reconnects; ``quiet_codes`` are statuses the caller handles itself.
        """
        client = self.connection.client
        if client is None:
            self.show_banner(self.connection.lost_message
                             or "not connected to matoptd: use Connect… first")
            if on_error:
                on_error(mc.ClientError("not connected"))
            return False

        def failed(exc: BaseException) -> None:
            quiet = isinstance(exc, grpc.RpcError) and exc.code() in quiet_codes
            if not quiet and not self.connection.report(exc):
                self.show_banner(f"{what} failed: {self.connection.describe(exc)}")
            if on_error:
                on_error(exc)

        self.tasks.submit(lambda: fn(client), on_done, failed)
        return True

    @Slot(str)
    def _show_upload(self, text: str) -> None:
        self.status(text)

    # =========================================================================================
    # Connection
    # =========================================================================================

    def connect_dialog(self) -> None:
        dialog = ConnectDialog(self.connection.settings or self.store.load_connection(), self)
        if dialog.exec():
            self.connect_to(dialog.result_settings())

    def connect_to(self, settings: ConnectionSettings, save: bool = True) -> None:
        """Connects in the background and (by default) remembers the settings.

        Scenes and jobs belong to a daemon: connecting to another one clears them.
        """
        if save:
            self.store.save_connection(settings)
        self._stop_watching()
        old = self.connection.settings
        if old is not None and old.server != settings.server:
            self.show_job(None)
            self.scene, self.parameters = None, []
            self.params.clear()
            self.references.set_sensors([])
            self.view.set_sensors([])
            self.jobs.set_jobs([])
            self._show_scene_label()
        self.connection_label.setText(f"connecting to {settings.server}…")
        self.workers_label.set_info(None)
        self.status(f"connecting to matoptd at {settings.server}…")
        self.connection.open(settings)

    def _describe_server(self, info: pb.ServerInfo) -> str:
        return (f"matoptd {info.version} at {self.connection.target} — user {info.user}, "
                f"{info.variant} on {info.device}")

    def _connected(self, info: pb.ServerInfo) -> None:
        self.settings.set_choices(workflow.choices(info))
        if self.banner.level == "error":
            self.banner.clear()
        self.connection_label.setText(self._describe_server(info))
        self.status(f"connected to {self._describe_server(info)}")
        self.refresh_jobs()
        if self.job is not None:  # the same daemon with other settings (e.g. a new token)
            self._reopen_job(self.job.name)
        self._update_actions()

    def _restored(self, info: pb.ServerInfo) -> None:
        self.settings.set_choices(workflow.choices(info))  # the daemon may have been updated
        self.banner.clear()
        self.connection_label.setText(self._describe_server(info))
        self.status(f"connection to matoptd at {self.connection.target} restored")
        self.refresh_jobs()
        if self.job is not None:  # missed events: fetch the job and its history again
            self._reopen_job(self.job.name)
        self._update_actions()

    def _lost(self, message: str) -> None:
        self.show_banner(message, "error")
        self.connection_label.setText(f"no connection to {self.connection.target}")
        self.workers_label.set_info(None)
        self._update_actions()

    def _connect_failed(self, message: str) -> None:
        self.show_banner(message, "error")
        self.connection_label.setText(f"not connected ({self.connection.target})")
        self.workers_label.set_info(None)
        self._update_actions()

    # =========================================================================================
    # Scene
    # =========================================================================================

    def open_scene_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open a Mitsuba scene",
                                              self.store.folder("scene"),
                                              "Mitsuba scenes (*.xml);;All files (*)")
        if path:
            self.store.set_folder("scene", os.path.dirname(path))
            self.open_scene(path)

    def open_cornell_box(self, overrides: dict[str, str] | None = None) -> None:
        """The daemon's built-in scene: nothing to upload."""
        self.open_scene(None, overrides)

    def open_scene(self, path: str | os.PathLike | None,
                   overrides: dict[str, str] | None = None) -> None:
        """Uploads the scene's bundle and creates it (the Open scene action, past its dialog).

        ``overrides`` default to the XML-defaults field above the table.
        """
        if overrides is None:
            try:
                overrides = parse_overrides(self.overrides.text())
            except ValueError as exc:
                self.show_banner(f"XML defaults: {exc}", "warning")
                return
            self.store.set_value("scene/overrides", self.overrides.text())
        label = os.path.basename(os.fspath(path)) if path else "the Cornell box"
        self.status(f"loading {label}…")
        self.scene_label.setText(f"<b>Loading {label}…</b>")

        def note(file: str, size: int) -> None:  # worker thread: only a queued signal
            self._upload_note.emit(f"uploading {file} ({size / 1e6:.1f} MB)…")

        self._call(f"loading {label}",
                   lambda c: _create_scene(c, os.fspath(path) if path else None,
                                           overrides, note),
                   self._scene_loaded,
                   on_error=lambda exc: self._show_scene_label())

    def _scene_loaded(self, loaded: tuple[pb.Scene, list[pb.Parameter]]) -> None:
        scene, parameters = loaded
        self.show_job(None)  # a new scene starts a new setup: the old job stays in the list
        self._set_scene(scene, parameters)
        self.status(f"loaded {scene.display_name} as {scene.name}: {len(parameters)} "
                    f"parameters, {len(scene.sensors)} sensor(s)")
        if scene.warnings:
            self.show_banner("; ".join(scene.warnings), "warning")
        elif self.banner.level in ("warning", "info"):
            self.banner.clear()
        self._render_scene_preview()

    def _set_scene(self, scene: pb.Scene, parameters: list[pb.Parameter]) -> None:
        self.scene, self.parameters = scene, parameters
        self._set_base_spec(None)
        self._set_initial_from(None)
        self.params.set_parameters(parameters)
        self.references.set_sensors(scene.sensors)
        self.view.set_sensors(scene.sensors)
        self.previews.clear()
        self._show_scene_label()
        self._update_images()
        self._update_actions()

    def _sensor_changed(self) -> None:
        self._update_images()
        sensor = self.view.sensor_index()
        if self.job is None and sensor is not None and sensor not in self.previews:
            self._render_scene_preview()

    def _show_scene_label(self) -> None:
        if self.scene is None:
            self.scene_label.setText("<b>No scene</b> — Open scene… or Cornell box")
            return
        s = self.scene
        overrides = ", ".join(f"{k}={v}" for k, v in sorted(s.overrides.items()))
        sensors = f"{len(s.sensors)} sensor{'' if len(s.sensors) == 1 else 's'}"
        self.scene_label.setText(f"<b>{s.display_name}</b> ({s.name}) — {sensors}"
                                 + (f" — {overrides}" if overrides else ""))
        self.scene_label.setToolTip(s.main_file or "built-in Cornell box")

    def _render_scene_preview(self) -> None:
        """The scene as loaded, for the chosen sensor: the user sees what they opened."""
        scene, sensor = self.scene, self.view.sensor_index()
        if scene is None or sensor is None:
            return

        def render(c: mc.Client):
            response = c.scenes.RenderScene(pb.RenderSceneRequest(
                name=scene.name, spp=SCENE_PREVIEW_SPP, sensors=[sensor]),
                timeout=CALL_TIMEOUT_S * 4)
            return self.cache.image(c, response.images[0].png_blob)

        def done(image) -> None:
            if self.scene is scene:
                self.previews[sensor] = (image, f"the scene as loaded ({SCENE_PREVIEW_SPP} spp)")
                self._update_images()

        self._call("rendering a preview", render, done)

    # =========================================================================================
    # References
    # =========================================================================================

    def _choose_references(self) -> None:
        self.references.choose_all()
        self.store.set_folder("references", self.references.start_folder)

    def set_reference_files(self, paths: Sequence[str | os.PathLike]) -> str | None:
        """Maps images to the sensors; returns (and shows) the problem if the count is off."""
        problem = self.references.set_files([os.fspath(p) for p in paths])
        if problem is None and self.banner.level == "warning":
            self.banner.clear()
        return problem

    def _references_changed(self) -> None:
        self._update_images()
        self._update_actions()

    # =========================================================================================
    # Starting a job
    # =========================================================================================

    def build_spec(self) -> pb.JobSpec:
        """The JobSpec of the setup, references not yet uploaded; ValueError says what is
        missing or malformed, as a sentence for the banner."""
        if self.scene is None:
            raise ValueError("open a scene first")
        parameters = self.params.specs()
        if not parameters:
            raise ValueError("select at least one parameter to optimize (tick its box in the "
                             "Optimize column)")
        if not self.references.references():
            raise ValueError(f"choose the reference images: one per sensor "
                             f"({len(self.scene.sensors)} for this scene)")
        base = self.base_spec if (self.base_spec is not None
                                  and self.base_spec.scene == self.scene.name) else None
        return workflow.build_spec(self.scene.name, parameters, self.settings.values(),
                                   base=base)

    def _set_base_spec(self, spec: pb.JobSpec | None, source: str = "") -> None:
        self.base_spec = spec
        kept = inherited(spec) if spec is not None else []
        self.kept_label.setText(f"Also kept from {source}: {', '.join(kept)}" if kept else "")
        self.kept_label.setVisible(bool(kept))

    def start_job(self) -> None:
        """Creates a job from the setup: uploads the local reference images (not those
        already on the server, as after opening a job to restart it) and starts watching."""
        if self._starting:
            return
        try:
            spec = self.build_spec()
        except ValueError as exc:
            self.show_banner(f"cannot start: {exc}", "warning")
            return
        references = self.references.references()
        initial_from = self.initial_from

        def create(c: mc.Client) -> pb.Job:
            # initial_from: large parameters continue from the result too
            return workflow.start_job(
                c, spec, references, initial_from,
                lambda f, n: self._upload_note.emit(f"uploading {f}…"), CALL_TIMEOUT_S * 2)

        def done(job: pb.Job) -> None:
            self._starting = False
            self._update_actions()
            if self.banner.level == "warning":
                self.banner.clear()
            self.status(f"started {job.name}")
            # The references are on the server now: a restart must not upload them again.
            self.references.set_from_spec(job.spec.references)
            # The table now shows what the job starts from (start values taken over from a
            # result included), so that a restart reproduces it plus the user's edits.
            self.params.apply_specs(job.spec.parameters)
            self._set_initial_from(None)
            self._set_base_spec(job.spec, job.name)
            self.show_job(job)
            self.refresh_jobs()

        def failed(exc: BaseException) -> None:
            self._starting = False
            self._update_actions()

        self._starting = True
        self._update_actions()
        self.status("starting the job…")
        self._call("starting the job", create, done, failed)

    restart_job = start_job  # the setup holds the opened job's spec with the user's edits

    # =========================================================================================
    # The job shown
    # =========================================================================================

    def open_job(self, name: str) -> None:
        """Shows a job from the list (any client's) and loads its spec into the setup, so it
        can be edited and restarted without uploading anything again."""
        known = self.scene.name if self.scene else None

        def done(fetched) -> None:
            job, scene, parameters, problem = fetched
            if scene is not None:
                self._set_scene(scene, parameters or [])
            if problem:
                self.show_banner(problem, "warning")
            elif job.spec.scene == (self.scene.name if self.scene else None):
                unknown = self.params.apply_specs(job.spec.parameters)
                self.references.set_from_spec(job.spec.references)
                self.settings.apply(job.spec)
                self._set_base_spec(job.spec, job.name)
                self._set_initial_from(None)
                if unknown:
                    self.show_banner(f"parameters of {job.name} not in its scene any more: "
                                     f"{', '.join(unknown)}", "warning")
            self.show_job(job)

        self.status(f"opening {name}…")
        self._call(f"opening {name}", lambda c: _fetch_job(c, mc.resource_name("jobs", name),
                                                           known), done)

    def show_job(self, job: pb.Job | None) -> None:
        """Shows ``job`` on the right and follows it (history first, then the live stream)."""
        self._stop_watching()
        self.job, self.result, self.latest, self.best_loss = job, None, None, None
        self.previews = {k: v for k, v in self.previews.items() if job is None}
        self.view.plot.clear()
        self.view.result_label.setText("")
        self.params.clear_current()
        self.jobs.set_current(job.name if job else None)
        self.view.show_job(job)
        if job is None:
            self.view.plot.set_target(None)
            self._update_title()
            self._update_images()
            self._update_actions()
            return
        self.view.plot.set_target(job.spec.min_error if job.spec.HasField("min_error") else None)
        best = workflow.best(job)
        if best is not None:
            self.best_loss = best[1]
            self.view.plot.set_best_iteration(best[0])
        self._update_title()
        self._load_history(job.name)
        self._watch(job.name)
        if job.state in mc.TERMINAL_STATES:
            self._fetch_result()
        self._update_images()
        self._update_actions()

    def _reopen_job(self, name: str) -> None:
        """After a reconnect: the job's state, the iterations missed, and a new stream."""
        def done(job: pb.Job) -> None:
            if self.job is not None and self.job.name == job.name:
                self._job_changed(job)
                self._load_history(job.name)
                self._watch(job.name)
        self._call(f"fetching {name}",
                   lambda c: c.jobs.GetJob(pb.GetJobRequest(name=name), timeout=CALL_TIMEOUT_S),
                   done)

    def _load_history(self, name: str) -> None:
        def done(response: pb.GetJobHistoryResponse) -> None:
            if self.job is None or self.job.name != name:
                return
            records = list(response.iterations)
            self.view.plot.extend((r.iteration, r.seconds, r.loss, _errors(r)) for r in records)
            if records and (self.latest is None
                            or records[-1].iteration > self.latest.iteration):
                self._iteration(records[-1], plot=False)
        self._call(f"fetching the history of {name}",
                   lambda c: c.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=name),
                                                  timeout=CALL_TIMEOUT_S), done)

    def _watch(self, name: str) -> None:
        client = self.connection.client
        if client is None:
            return
        self._stop_watching()
        self._watch_generation += 1
        watcher = JobWatcher(client, name, self._watch_generation, self)
        queued = Qt.ConnectionType.QueuedConnection
        watcher.event.connect(self._watch_event, queued)
        watcher.failed.connect(self._watch_failed, queued)
        watcher.ended.connect(self._watch_ended, queued)
        self._watcher = watcher
        watcher.start()

    def _stop_watching(self) -> None:
        if self._watcher is not None:
            self._watcher.stop()
            self._old_watchers.append(self._watcher)
            self._watcher = None
        self._watch_generation += 1  # whatever the old one still queued is dropped

    @Slot(int, object)
    def _watch_event(self, generation: int, event: pb.JobEvent) -> None:
        if generation != self._watch_generation or self.job is None:
            return
        if event.HasField("job"):
            self._job_changed(event.job)
        else:
            self._iteration(event.iteration)

    @Slot(int, object)
    def _watch_failed(self, generation: int, exc: BaseException) -> None:
        if generation != self._watch_generation or self.job is None:
            return
        if not self.connection.report(exc):
            self.show_banner(f"following {self.job.name} failed: "
                             f"{self.connection.describe(exc)}")

    @Slot(int)
    def _watch_ended(self, generation: int) -> None:
        self._old_watchers = [w for w in self._old_watchers if w.isRunning()]
        if self._watcher is not None and self._watcher.generation == generation:
            self._old_watchers.append(self._watcher)
            self._watcher = None

    def _job_changed(self, job: pb.Job) -> None:
        previous = self.job
        if (previous is not None and previous.name == job.name
                and job.update_time.ToNanoseconds() < previous.update_time.ToNanoseconds()):
            # A Pause/Resume reply that the watch stream overtook (the worker acted on the
            # request before the reply reached this thread): showing it would undo the newer
            # state, and no later state event would come to correct it.
            return
        self.job = job
        self.jobs.update_job(job)
        self.view.show_job(job)
        best = workflow.best(job)  # the daemon's, sent after each batch of iterations
        if best is not None:
            self.best_loss = best[1]
            self.view.plot.set_best_iteration(best[0])
        self._update_title()
        self._update_actions()
        changed = previous is None or previous.state != job.state
        if not changed:
            return
        if job.state in mc.TERMINAL_STATES:
            self._load_history(job.name)  # the complete curve, whatever the stream missed
            self._fetch_result()
            if job.state == pb.JOB_STATE_FAILED:
                self.show_banner(f"{job.name} FAILED: {job.error or 'no reason given'}")
            else:
                self.status(f"{job.name} {mc.state_name(job.state)}"
                            + (f" ({job.stop_reason})" if job.stop_reason else ""))
        elif job.state == pb.JOB_STATE_INTERRUPTED:
            # The daemon stopped while the job ran: is it still there at all?
            self.connection.check_now()
            self.status(f"{job.name} was interrupted: Resume continues it from its last "
                        f"checkpoint")

    def _iteration(self, record: pb.IterationRecord, plot: bool = True) -> None:
        if plot:
            self.view.plot.add(record.iteration, record.seconds, record.loss, _errors(record))
        if self.latest is not None and record.iteration < self.latest.iteration:
            return
        self.latest = record
        done = record.iteration + 1  # records count from 0
        self.view.progress.setValue(min(done, self.view.progress.maximum()))
        self.view.set_numbers(done, record.loss, self.best_loss, record.seconds)
        if self.result is None:
            self.params.show_current(record.parameters)

    def _update_title(self) -> None:
        parts = ["matopt"]
        if self.scene:
            parts.append(self.scene.display_name)
        if self.job:
            parts.append(f"{self.job.name.rsplit('/', 1)[-1]} ({mc.state_name(self.job.state)})")
        self.setWindowTitle(" — ".join(parts))

    # =========================================================================================
    # Job control
    # =========================================================================================

    def pause_job(self) -> None:
        self._control("PauseJob", pb.PauseJobRequest, "pausing")

    def resume_job(self) -> None:
        self._control("ResumeJob", pb.ResumeJobRequest, "resuming")

    def cancel_job(self) -> None:
        self._control("CancelJob", pb.CancelJobRequest, "cancelling")

    def _control(self, rpc: str, request_type, verb: str) -> None:
        """Pause/resume/cancel act at the next iteration boundary; the stream shows when."""
        if self.job is None:
            return
        name = self.job.name

        def done(job: pb.Job) -> None:
            if self.job is None or self.job.name != name:
                return
            self._job_changed(job)
            self.status(f"{verb} {name}: takes effect at the next iteration")
            if self._watcher is None and job.state not in mc.TERMINAL_STATES:
                self._watch(name)  # e.g. resuming an INTERRUPTED job whose stream had ended

        self._call(f"{verb} {name}", lambda c: getattr(c.jobs, rpc)(
            request_type(name=name), timeout=CALL_TIMEOUT_S), done)

    # =========================================================================================
    # Results
    # =========================================================================================

    def set_which(self, which: str) -> None:
        """"best" or "last": which iteration's result is shown (and exported)."""
        (self.view.last_radio if which == "last" else self.view.best_radio).setChecked(True)

    def set_sensor(self, sensor: int) -> None:
        position = self.view.sensor.findData(sensor)
        if position < 0:
            raise ValueError(f"no sensor {sensor}")
        self.view.sensor.setCurrentIndex(position)

    def _which_changed(self) -> None:
        if self.job is not None and (self.result is not None
                                     or self.job.state in mc.TERMINAL_STATES):
            self._fetch_result()

    def _fetch_result(self) -> None:
        if self.job is None:
            return
        name, which = self.job.name, self.view.which()

        def done(result: pb.JobResult) -> None:
            if self.job is None or self.job.name != name or self.view.which() != which:
                return
            self.result = result
            label = "best" if result.which != pb.WHICH_LAST else "last"
            self.view.result_label.setText(f"{label}: iteration {result.iteration}, "
                                           f"loss {result.loss:.4g}")
            self.params.show_current(result.parameters)
            self._update_images()
            self._update_actions()

        def failed(exc: BaseException) -> None:
            if isinstance(exc, grpc.RpcError) and exc.code() == \
                    grpc.StatusCode.FAILED_PRECONDITION and self.job is not None \
                    and self.job.name == name:
                self.result = None
                self.view.result_label.setText("no results: " + _details(exc))
                self._update_images()
                self._update_actions()

        self._call(f"fetching the result of {name}",
                   lambda c: c.jobs.GetJobResult(pb.GetJobResultRequest(
                       name=name, which=pb.WHICH_LAST if which == "last" else pb.WHICH_BEST),
                       timeout=CALL_TIMEOUT_S),
                   done, failed, quiet_codes=(grpc.StatusCode.FAILED_PRECONDITION,))

    def use_result_as_start(self) -> None:
        """The shown result becomes the next job's start: its values go into the table
        (scalars and colours, to see and edit), and the job is created with
        ``initial_from_job`` so that parameters too large for the table (textures, vertex
        arrays) continue from the result as well, without uploading anything."""
        if self.result is None or self.job is None:
            return
        count = 0
        for value in self.result.parameters:
            if value.value and value.key in self.params.keys():
                self.params.set_initial(value.key, value.value)
                count += 1
        self._set_initial_from((self.job.name, self.result.which or pb.WHICH_BEST))
        self.status(f"{count} start value(s) taken from {self.job.name} "
                    f"(iteration {self.result.iteration}); edit and Start")

    def _set_initial_from(self, source: tuple[str, int] | None) -> None:
        self.initial_from = source
        if source is not None:
            which = "last" if source[1] == pb.WHICH_LAST else "best"
            self.continue_label.setText(f"Continues from {source[0]} ({which}) where the "
                                        f"table sets no start value")
        self.continue_label.setVisible(source is not None)
        self.continue_clear.setVisible(source is not None)

    def export_dialog(self) -> None:
        if self.job is None:
            return
        directory = QFileDialog.getExistingDirectory(
            self, f"Export {self.job.name} ({self.view.which()}) to", self.store.folder("export"))
        if directory:
            self.store.set_folder("export", directory)
            self.export_to(directory)

    def export_to(self, directory: str | os.PathLike) -> None:
        """Writes the same files as ``matopt job export`` (parameters.json, images,
        history.csv) for the best or last iteration, whichever is shown."""
        if self.job is None:
            return
        name, which, folder = self.job.name, self.view.which(), os.fspath(directory)
        self.status(f"exporting {name} to {folder}…")

        def done(export) -> None:
            self.status(f"exported {len(export.files)} files of {name} ({which} iteration "
                        f"{export.result.iteration}) to {folder}", 15000)
            self.show_banner(f"exported {name} ({which}) to {folder}", "info")

        self._call(f"exporting {name}", lambda c: export_job(c, name, folder, which), done)

    # =========================================================================================
    # Images
    # =========================================================================================

    def _update_images(self) -> None:
        """Reference beside render for the chosen sensor: the result's images when there are
        results, else the reference file and the latest preview."""
        sensor = self.view.sensor_index()
        ref_pane, render_pane = self.view.reference, self.view.render
        if sensor is None:
            ref_pane.set_placeholder("no scene")
            render_pane.set_placeholder("no scene")
            return
        images = {(i.sensor, i.role): i for i in (self.result.images if self.result else [])}

        reference = images.get((sensor, "reference"))
        if reference is not None:
            self._show_blob(ref_pane, reference.png_blob, f"sensor {sensor}, as the job saw it")
        else:
            self._show_reference_file(sensor)

        role = self.view.role.currentText()
        rendered = images.get((sensor, role))
        if rendered is not None:
            label = "best" if self.result.which != pb.WHICH_LAST else "last"
            iteration = f"{label} iteration {self.result.iteration}"
            caption = {"initial": "initial values",
                       "error": f"|optimized − reference|, {iteration}"}.get(
                           role, f"{role}, {iteration}")
            self._show_blob(render_pane, rendered.png_blob, caption)
        elif self.result is not None:
            render_pane.set_placeholder(f"no {role} image of sensor {sensor} in the result")
        elif sensor in self.previews:
            image, caption = self.previews[sensor]
            self._wanted[id(render_pane)] = None
            render_pane.set_image(image, caption)
        else:
            render_pane.set_placeholder("no render yet" if self.job is None or self.job.state
                                        in mc.TERMINAL_STATES else
                                        "waiting for the first preview…")

    def _show_reference_file(self, sensor: int) -> None:
        pane = self.view.reference
        ref = self.references.reference(sensor)
        if ref is None:
            self._wanted[id(pane)] = None
            pane.set_placeholder(f"no reference image for sensor {sensor}")
            return
        key = ref.image
        if pane.key == key:
            return
        exr_note = (f"{ref.filename}: OpenEXR, shown once the job has results"
                    if ref.filename.lower().endswith(".exr") else "cannot display this image")
        self._wanted[id(pane)] = key
        if not ref.on_server:
            path = ref.image
            self.tasks.submit(lambda: read_image(path),
                              lambda image: self._deliver(pane, key, image, ref.filename,
                                                          exr_note))
        else:
            blob = ref.image
            self._call("fetching the reference image",
                       lambda c: self.cache.image(c, blob),
                       lambda image: self._deliver(pane, key, image, ref.filename, exr_note))

    def _show_blob(self, pane, blob: str, caption: str) -> None:
        if pane.key == blob:
            pane.caption.setText(caption)
            return
        self._wanted[id(pane)] = blob
        self._call("fetching an image", lambda c: self.cache.image(c, blob),
                   lambda image: self._deliver(pane, blob, image, caption))

    def _deliver(self, pane, key: str, image, caption: str,
                 placeholder: str = "cannot display this image") -> None:
        if self._wanted.get(id(pane)) == key:  # not superseded by another sensor or result
            pane.set_image(image, caption, key=key, placeholder=placeholder)

    def _preview_tick(self) -> None:
        """While the job runs: render the latest iterate for the chosen sensor at low spp.

        RenderScene takes its turn on the daemon's device between iterations, so it slows the
        job down; a render that took longer than a fifth of the interval stretches the
        interval, keeping the cost to about 20% at most.
        """
        job, record, sensor = self.job, self.latest, self.view.sensor_index()
        if (self._preview_busy or job is None or job.state != pb.JOB_STATE_RUNNING or record is None
                or sensor is None or not self.view.live.isChecked()
                or not self.connection.usable or self.result is not None):
            return
        sent = {p.key for p in record.parameters}
        missing = [p.key for p in job.spec.parameters if p.key not in sent]
        if missing:
            self.view.render.set_placeholder(
                "no live preview: large parameters (" + ", ".join(missing[:3]) + ") are not "
                "sent per iteration; the render appears with the results")
            return
        values = [pb.ParameterValue(key=p.key, value=p.value, shape=p.shape)
                  for p in record.parameters]
        spp, iteration, started = self.preview_spp, record.iteration, time.monotonic()

        def render(c: mc.Client):
            response = c.scenes.RenderScene(pb.RenderSceneRequest(
                name=job.spec.scene, parameters=values, spp=spp, sensors=[sensor]),
                timeout=CALL_TIMEOUT_S * 4)
            return self.cache.image(c, response.images[0].png_blob), time.monotonic() - started

        def done(rendered) -> None:
            self._preview_busy = False
            image, seconds = rendered
            base = int(self.preview_interval_s * 1000)
            self.preview_timer.setInterval(max(base, int(seconds * 5000)))
            if self.job is None or self.job.name != job.name:
                return
            self.previews[sensor] = (image, f"preview of iteration {iteration} ({spp} spp, "
                                            f"{seconds:.2f} s)")
            self._update_images()

        def failed(exc: BaseException) -> None:
            self._preview_busy = False

        self._preview_busy = True
        self._call("rendering a preview", render, done, failed)

    # =========================================================================================
    # Jobs list
    # =========================================================================================

    def refresh_jobs(self) -> None:
        """ListJobs (every page) into the list; skipped while the last refresh is under way."""
        if self.jobs_loading or not self.connection.usable:
            return

        def done(jobs: list[pb.Job]) -> None:
            self.jobs_loading = False
            self.jobs.set_jobs(jobs)

        def failed(exc: BaseException) -> None:
            self.jobs_loading = False

        self.jobs_loading = True
        self._call("listing jobs",
                   lambda c: mc.list_all(lambda r: c.jobs.ListJobs(r, timeout=CALL_TIMEOUT_S),
                                         pb.ListJobsRequest(page_size=200), "jobs"),
                   done, failed)

    # =========================================================================================
    # State of the buttons, and closing
    # =========================================================================================

    def _update_actions(self) -> None:
        connected = self.connection.client is not None
        job = self.job
        can_start = connected and self.scene is not None and not self._starting
        self.start_action.setEnabled(can_start)
        self.start_button.setEnabled(can_start)
        self.start_button.setText("Starting…" if self._starting else "Start")
        self.open_action.setEnabled(connected)
        self.cornell_action.setEnabled(connected)
        self.references_action.setEnabled(self.scene is not None)
        running = job is not None and job.state in (pb.JOB_STATE_QUEUED, pb.JOB_STATE_RUNNING)
        self.pause_action.setEnabled(running)
        self.resume_action.setEnabled(job is not None and job.state in (pb.JOB_STATE_PAUSED,
                                                                         pb.JOB_STATE_INTERRUPTED))
        self.cancel_action.setEnabled(job is not None and job.state not in mc.TERMINAL_STATES)
        has_result = self.result is not None
        self.export_action.setEnabled(has_result)
        self.view.export_button.setEnabled(has_result)
        self.view.use_result_button.setEnabled(has_result and self.scene is not None
                                               and job is not None
                                               and job.spec.scene == self.scene.name)

    def closeEvent(self, event: QCloseEvent) -> None:  # noqa: N802 - Qt's name
        self.shutdown()
        super().closeEvent(event)

    def shutdown(self) -> None:
        """Stops timers, the stream and the pool; the jobs keep running on the daemon."""
        if self._shut_down:
            return
        self._shut_down = True
        self.store.qsettings.setValue("window/geometry", self.saveGeometry())
        self.store.qsettings.sync()
        self.jobs_timer.stop()
        self.preview_timer.stop()
        self._stop_watching()
        for watcher in self._old_watchers:
            watcher.stop()
        self.connection.close()
        self.tasks.shutdown()


def _errors(record: pb.IterationRecord) -> dict[str, float]:
    """Each parameter's relative error against the job's ground truth (none without it)."""
    return {e.key: e.relative for e in record.errors}


def inherited(spec: pb.JobSpec) -> list[str]:
    """The settings of ``spec`` that the setup has no field for and that differ from the
    defaults, in words (what a restart keeps without showing it)."""
    out = []
    if spec.seed:
        out.append(f"seed {spec.seed}")
    if spec.HasField("learning_rate"):
        out.append(f"default learning rate {spec.learning_rate:g}")
    if spec.film_height:
        out.append(f"film height {spec.film_height} px")
    if spec.ground_truth:
        out.append(f"ground truth of {len(spec.ground_truth)} parameter(s)")
    if spec.image_error_every:
        out.append(f"image error every {spec.image_error_every} iterations")
    return out


def _details(exc: grpc.RpcError) -> str:
    return " ".join((exc.details() or "").split())


# =============================================================================================
# Entry point
# =============================================================================================


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="matopt-qt",
        description="Desktop client of matoptd: load a scene, pick parameters and reference "
                    "images, optimize, watch and export. The token is taken from the connect "
                    "dialog or MATOPT_TOKEN, never from the command line (where other users "
                    "could read it).")
    parser.add_argument("--server", help="matoptd address host:port (default: the last one "
                                         "used, else MATOPT_SERVER, else 127.0.0.1:50051)")
    parser.add_argument("--tls-ca", help="PEM file of the CA that signed the daemon's "
                                         "certificate (default: the last one used)")
    parser.add_argument("scene", nargs="?", help="a scene XML to open after connecting")
    return parser.parse_args(list(argv))


def main(argv: Sequence[str] | None = None) -> int:
    """``matopt-qt``: opens the window and connects with the remembered settings."""
    args = parse_args(sys.argv[1:] if argv is None else argv)
    broken = pyside_check.problem()
    if broken:
        print(f"matopt-qt: error: {broken}", file=sys.stderr)
        return 1
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s "
                                                   "%(message)s")
    app = QApplication.instance() or QApplication(sys.argv[:1])
    app.setOrganizationName("matopt")
    app.setApplicationName("matopt-qt")
    store = SettingsStore()
    window = MainWindow(store)
    settings = store.load_connection()
    if args.server:
        settings.server = args.server
    if args.tls_ca:
        settings.tls_ca = args.tls_ca
    if os.environ.get("MATOPT_TOKEN") and not settings.token:
        settings.token = os.environ["MATOPT_TOKEN"]
    window.show()
    if store.has_saved_connection() or args.server or os.environ.get("MATOPT_SERVER"):
        window.connect_to(settings, save=bool(args.server or args.tls_ca))
    else:
        QTimer.singleShot(0, window.connect_dialog)
    if args.scene:
        scene = os.path.abspath(args.scene)
        window.connection.connected.connect(lambda _: window.open_scene(scene),
                                            Qt.ConnectionType.SingleShotConnection)
    return app.exec()
