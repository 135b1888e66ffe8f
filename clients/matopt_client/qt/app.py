"""The main window: the thesis tool's workflow on top of the matoptd API.

Left, the jobs on the server; in the middle, the setup of the next job (scene, parameter
table, one reference per sensor, loss and iterations); right, the job being shown (progress,
pause/resume/cancel, reference beside render, loss against seconds, best/last, export).

The window owns no rendering and no job: the daemon does. Every call to it runs on a worker
thread (:mod:`matopt_client.qt.worker`) and comes back as a callback here, so the window keeps
painting, and says so in a banner, when the daemon is slow or gone.

This module builds the window and wires its parts: the toolbar (:mod:`matopt_client.qt.toolbar`), the
setup pane (:mod:`matopt_client.qt.setup_panel`), the job pane (:mod:`matopt_client.qt.job_view`), the jobs
list, and the behaviour of each, grouped by what it is about: :mod:`matopt_client.qt.scene_control`,
:mod:`matopt_client.qt.job_control` and :mod:`matopt_client.qt.results_control`. Here: the connection,
messages, the jobs list's refresh, which buttons are enabled, and closing.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

import grpc
from PySide6.QtCore import QByteArray, QStandardPaths, Qt, QTimer, Signal, Slot
from PySide6.QtGui import QCloseEvent
from PySide6.QtWidgets import QApplication, QDockWidget, QLabel, QMainWindow, QSplitter, \
    QVBoxLayout, QWidget

from matopt_client import client as mc
from matopt_client import workflow
from matopt_client.qt import pyside_check
from matopt_client.qt.banner import Banner
from matopt_client.qt.connection import (ConnectDialog, Connection, ConnectionSettings, SettingsStore)
from matopt_client.qt.images import BlobCache
from matopt_client.qt.job_control import JobControl
from matopt_client.qt.job_view import JobView
from matopt_client.qt.jobs_list import JobsList
from matopt_client.qt.results_control import ResultsControl
from matopt_client.qt.scene_control import SceneControl
from matopt_client.qt.setup_panel import SetupPanel
from matopt_client.qt.toolbar import add_toolbar
from matopt_client.qt.worker import CALL_TIMEOUT_S, JobWatcher, Tasks
from matopt_client.qt.workers_label import WorkersLabel
from matopt_api.v1 import matopt_pb2 as pb

log = logging.getLogger(__name__)


class MainWindow(SceneControl, JobControl, ResultsControl, QMainWindow):
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
        actions = add_toolbar(self, self.store.value("scene/overrides"))
        self.connect_action, self.open_action = actions.connect, actions.open
        self.cornell_action, self.references_action = actions.cornell, actions.references
        self.start_action, self.pause_action = actions.start, actions.pause
        self.resume_action, self.cancel_action = actions.resume, actions.cancel
        self.export_action, self.overrides = actions.export, actions.overrides

        central = QWidget()
        outer = QVBoxLayout(central)
        outer.setContentsMargins(6, 4, 6, 4)
        self.banner = Banner()
        outer.addWidget(self.banner)
        splitter = QSplitter(Qt.Orientation.Horizontal)
        outer.addWidget(splitter, 1)
        self.setCentralWidget(central)

        # Setup of the next job; its widgets go by the window's names too (tests, scripts).
        self.setup = SetupPanel()
        self.scene_label, self.params = self.setup.scene_label, self.setup.params
        self.references, self.settings = self.setup.references, self.setup.settings
        self.kept_label, self.continue_label = self.setup.kept_label, self.setup.continue_label
        self.start_button = self.setup.start_button
        self.params.changed.connect(self._update_actions)
        self.references.start_folder = self.store.folder("references")
        self.references.problem.connect(lambda text: self.show_banner(text, "warning"))
        self.references.changed.connect(self._references_changed)
        self.start_button.clicked.connect(self.start_job)
        splitter.addWidget(self.setup)

        # The job being shown.
        self.view = JobView()
        self.view.pause_button.clicked.connect(self.pause_job)
        self.view.resume_button.clicked.connect(self.resume_job)
        self.view.cancel_button.clicked.connect(self.cancel_job)
        self.view.export_button.clicked.connect(self.export_dialog)
        self.view.estimate_button.clicked.connect(self.estimate_errors)
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

        self.tasks.submit(lambda: fn(client), on_done, failed, what)
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
            self.setup.show_scene(None)
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
        self.view.estimate_button.setEnabled(connected and job is not None
                                             and job.state == pb.JOB_STATE_PAUSED)
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
                                         f"used, else MATOPT_SERVER, else {mc.DEFAULT_SERVER})")
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
