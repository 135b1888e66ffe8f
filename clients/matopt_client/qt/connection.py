"""Where the app connects, remembered between runs, and the connection's health.

A daemon on a shared workstation restarts (updates, a crash, a reboot), and a laptop loses the
network; a window that then hangs or silently shows stale numbers is worse than useless. So
the connection is watched: any call that fails because the daemon cannot be reached marks it
lost (the window shows a banner naming the address and the gRPC status), and from then on a
fresh channel is tried every few seconds until the daemon answers again.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import grpc
from PySide6.QtCore import QObject, QSettings, QTimer, Signal
from PySide6.QtWidgets import (QCheckBox, QDialog, QDialogButtonBox, QFileDialog, QFormLayout,
                               QHBoxLayout, QLineEdit, QPushButton, QWidget)

from matopt_client import client as mc
from matopt_client.qt.worker import Tasks, describe
from matopt_api.v1 import matopt_pb2 as pb

log = logging.getLogger(__name__)

DEFAULT_SERVER = mc.DEFAULT_SERVER
PROBE_TIMEOUT_S = 3.0


@dataclass
class ConnectionSettings:
    """Server address, token and TLS CA. The token is left out of ``repr`` so that it can
    never end up in a log line or a traceback that prints these settings."""

    server: str = DEFAULT_SERVER
    token: str | None = field(default=None, repr=False)
    tls_ca: str | None = None
    remember_token: bool = True

    @property
    def has_token(self) -> bool:
        return bool(self.token)


class SettingsStore:
    """The app's QSettings: connection settings and the folders last used in file dialogs.

    Tests pass their own QSettings (an .ini file in a temporary folder) so that they never
    read or overwrite the user's real settings.
    """

    def __init__(self, settings: QSettings | None = None) -> None:
        self.qsettings = settings if settings is not None else QSettings("matopt", "matopt-qt")

    def load_connection(self) -> ConnectionSettings:
        """Saved settings, else the CLI's environment variables, else the local default.

        Saved settings win over the environment: what the user typed into the connect dialog
        last time is what they expect, even in a shell that exports MATOPT_SERVER for the CLI.
        """
        s = self.qsettings
        server = str(s.value("connection/server", "") or "")
        if server:
            token = str(s.value("connection/token", "") or "") or None
            tls_ca = str(s.value("connection/tls_ca", "") or "") or None
            remember = str(s.value("connection/remember_token", "true")).lower() == "true"
            return ConnectionSettings(server, token, tls_ca, remember)
        return ConnectionSettings(os.environ.get("MATOPT_SERVER") or DEFAULT_SERVER,
                                  os.environ.get("MATOPT_TOKEN") or None,
                                  os.environ.get("MATOPT_TLS_CA") or None)

    def has_saved_connection(self) -> bool:
        return bool(self.qsettings.value("connection/server", ""))

    def save_connection(self, settings: ConnectionSettings) -> None:
        """Stores the settings; the token only when the user asked to remember it.

        The settings file holds the token in plain text, as the CLI's users keep theirs in
        the environment; it is made readable by its owner only.
        """
        s = self.qsettings
        s.setValue("connection/server", settings.server)
        s.setValue("connection/tls_ca", settings.tls_ca or "")
        s.setValue("connection/remember_token", "true" if settings.remember_token else "false")
        if settings.remember_token and settings.token:
            s.setValue("connection/token", settings.token)
        else:
            s.remove("connection/token")
        s.sync()
        restrict_to_owner(s.fileName())

    def folder(self, purpose: str) -> str:
        """The folder a file dialog for ``purpose`` ("scene", "references", ...) opened last."""
        return str(self.qsettings.value(f"folders/{purpose}", "") or "")

    def set_folder(self, purpose: str, path: str) -> None:
        self.qsettings.setValue(f"folders/{purpose}", path)

    def value(self, key: str, default: str = "") -> str:
        return str(self.qsettings.value(key, default) or default)

    def set_value(self, key: str, value: str) -> None:
        self.qsettings.setValue(key, value)


def restrict_to_owner(path: str) -> None:
    """chmod 600 on a settings file (on Windows, QSettings uses the per-user registry)."""
    if os.name == "posix" and path and Path(path).is_file():
        try:
            os.chmod(path, 0o600)
        except OSError as exc:
            log.warning("cannot restrict the permissions of %s: %s", path, exc.strerror)


def is_connection_failure(exc: BaseException, deadline_counts: bool = False) -> bool:
    """Whether a failed call means the daemon cannot be reached (as opposed to refused it).

    UNAVAILABLE is a refused or broken connection. DEADLINE_EXCEEDED means a daemon that
    stopped answering only for the probe (a call that is cheap by design); a long call such
    as loading a big scene may simply take longer than its deadline.
    """
    if isinstance(exc, mc.Unreachable):
        return True
    if isinstance(exc, grpc.RpcError) and hasattr(exc, "code"):
        codes = [grpc.StatusCode.UNAVAILABLE]
        if deadline_counts:
            codes.append(grpc.StatusCode.DEADLINE_EXCEEDED)
        return exc.code() in codes
    return False


def redact(text: str, token: str | None) -> str:
    """The text with the token blanked out: defence in depth for every message shown."""
    return text.replace(token, "<token>") if token else text


class Connection(QObject):
    """The one client the window uses, and whether the daemon is reachable.

    Signals (all on the GUI thread): ``connected(ServerInfo)`` after :meth:`open` succeeded,
    ``restored(ServerInfo)`` after a lost connection came back (with a fresh channel: gRPC's
    own reconnect back-off grows to minutes), ``lost(str)`` with the message to show, and
    ``failed(str)`` when the daemon refused the connection (e.g. an unknown token), which
    retrying cannot fix. ``info_received(ServerInfo)`` carries every fresh GetServerInfo answer,
    on (re)connecting and from each probe, so what it reports (the workers' states) stays
    current at no extra call.
    """

    connected = Signal(object)
    restored = Signal(object)
    lost = Signal(str)
    failed = Signal(str)
    info_received = Signal(object)

    def __init__(self, tasks: Tasks, probe_interval_s: float = 5.0,
                 retry_interval_s: float = 2.0, parent: QObject | None = None) -> None:
        super().__init__(parent)
        self.tasks = tasks
        self.probe_interval_s, self.retry_interval_s = probe_interval_s, retry_interval_s
        self.settings: ConnectionSettings | None = None
        self.client: mc.Client | None = None
        self.info: pb.ServerInfo | None = None
        self.lost_message: str | None = None
        self._generation = 0
        self._busy = False  # a probe or reconnect attempt is under way
        self._timer = QTimer(self)
        self._timer.timeout.connect(self._tick)

    # -- state ---------------------------------------------------------------------------------

    @property
    def target(self) -> str:
        return self.settings.server if self.settings else ""

    @property
    def usable(self) -> bool:
        """Connected and not lost: calls are worth making."""
        return self.client is not None and self.lost_message is None

    def describe(self, exc: BaseException) -> str:
        """:func:`describe` with the token redacted."""
        return redact(describe(exc), self.settings.token if self.settings else None)

    # -- opening -------------------------------------------------------------------------------

    def open(self, settings: ConnectionSettings) -> None:
        """Connects in the background; the outcome arrives as a ``connected``, ``lost`` or
        ``failed`` signal."""
        self._generation += 1
        generation = self._generation
        self._drop_client()
        self.settings, self.info, self.lost_message = settings, None, None
        self._busy = True
        self.tasks.submit(lambda: _connect(settings),
                          lambda client: self._opened(generation, client, first=True),
                          lambda exc: self._attempt_failed(generation, exc, first=True),
                          "connecting")

    def close(self) -> None:
        self._generation += 1
        self._timer.stop()
        self._drop_client()

    def _drop_client(self) -> None:
        if self.client is not None:
            self.client.close()  # cancels the old channel's calls; their callers see an error
            self.client = None

    def _opened(self, generation: int, client: mc.Client, first: bool) -> None:
        self._busy = False
        if generation != self._generation:
            client.close()
            return
        old, self.client, self.info = self.client, client, client.info
        if old is not None:
            old.close()
        was_lost, self.lost_message = self.lost_message, None
        self._schedule(self.probe_interval_s)
        log.info("connected to matoptd at %s as %s", client.target, client.info.user)
        self.info_received.emit(client.info)
        if first and not was_lost:
            self.connected.emit(client.info)
        else:
            self.restored.emit(client.info)

    def _attempt_failed(self, generation: int, exc: BaseException, first: bool) -> None:
        self._busy = False
        if generation != self._generation:
            return
        if is_connection_failure(exc, deadline_counts=True):
            if first:
                self._mark_lost(f"{self.describe(exc)}", prefix=False)
            self._schedule(self.retry_interval_s)
            return
        # The daemon answered but refused (UNAUTHENTICATED, a bad CA file, ...): retrying
        # with the same settings cannot help, the user has to change them.
        self._timer.stop()
        message = f"cannot connect to matoptd at {self.target}: {self.describe(exc)}"
        self.lost_message = message
        self.failed.emit(message)

    # -- health --------------------------------------------------------------------------------

    def report(self, exc: BaseException, deadline_counts: bool = False) -> bool:
        """Called with any failed call's exception; True if it meant the daemon is unreachable
        (then the lost-connection banner is up and reconnecting has begun)."""
        if not is_connection_failure(exc, deadline_counts) or self.settings is None:
            return False
        if self.lost_message is None:
            detail = self.describe(exc)
            if isinstance(exc, grpc.RpcError) and exc.code() == grpc.StatusCode.DEADLINE_EXCEEDED:
                detail = f"DEADLINE_EXCEEDED: no answer within {PROBE_TIMEOUT_S:g} s"
            self._mark_lost(detail)
            self._schedule(self.retry_interval_s)
        return True

    def check_now(self) -> None:
        """Probes (or retries) at once instead of at the next tick, e.g. when a job stopped."""
        self._tick()

    def _mark_lost(self, detail: str, prefix: bool = True) -> None:
        head = f"lost connection to matoptd at {self.target}: " if prefix else ""
        self.lost_message = (f"{head}{detail} — retrying every {self.retry_interval_s:g} s")
        log.warning("%s", self.lost_message)
        self.lost.emit(self.lost_message)

    def _schedule(self, seconds: float) -> None:
        self._timer.start(max(50, int(seconds * 1000)))

    def _tick(self) -> None:
        if self._busy or self.settings is None:
            return
        generation = self._generation
        if self.lost_message is not None:
            settings = self.settings
            self._busy = True
            self.tasks.submit(lambda: _connect(settings),
                              lambda client: self._opened(generation, client, first=False),
                              lambda exc: self._attempt_failed(generation, exc, first=False),
                              "reconnecting")
            return
        client = self.client
        if client is None:
            return
        self._busy = True
        self.tasks.submit(
            lambda: client.server.GetServerInfo(pb.GetServerInfoRequest(),
                                                timeout=PROBE_TIMEOUT_S),
            lambda info: self._probed(generation, info),
            lambda exc: self._probe_failed(generation, exc), "probing the daemon")

    def _probed(self, generation: int, info: pb.ServerInfo) -> None:
        self._busy = False
        if generation == self._generation:
            self.info = info
            self.info_received.emit(info)

    def _probe_failed(self, generation: int, exc: BaseException) -> None:
        self._busy = False
        if generation == self._generation:
            self.report(exc, deadline_counts=True)


def _connect(settings: ConnectionSettings) -> mc.Client:
    return mc.connect(settings.server, settings.token, settings.tls_ca,
                      probe_timeout=PROBE_TIMEOUT_S)


class ConnectDialog(QDialog):
    """Server, token and TLS CA, as the CLI's --server/--token/--tls-ca take them.

    The token field never shows its text (a screen share or a screenshot must not leak it).
    """

    def __init__(self, settings: ConnectionSettings, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setWindowTitle("Connect to matoptd")
        form = QFormLayout(self)
        self.server = QLineEdit(settings.server)
        self.server.setPlaceholderText(DEFAULT_SERVER)
        self.server.setToolTip("host:port of the daemon (the CLI's --server / MATOPT_SERVER)")
        form.addRow("Server", self.server)
        self.token = QLineEdit(settings.token or "")
        self.token.setEchoMode(QLineEdit.EchoMode.Password)
        self.token.setPlaceholderText("none: a daemon serving a single local user")
        form.addRow("Token", self.token)
        self.remember = QCheckBox("Remember the token on this computer")
        self.remember.setChecked(settings.remember_token)
        form.addRow("", self.remember)
        row = QHBoxLayout()
        self.tls_ca = QLineEdit(settings.tls_ca or "")
        self.tls_ca.setPlaceholderText("none: plaintext (loopback or a trusted network only)")
        browse = QPushButton("Browse…")
        browse.clicked.connect(self._browse)
        row.addWidget(self.tls_ca)
        row.addWidget(browse)
        form.addRow("TLS CA", row)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok
                                   | QDialogButtonBox.StandardButton.Cancel)
        buttons.button(QDialogButtonBox.StandardButton.Ok).setText("Connect")
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        form.addRow(buttons)
        self.resize(520, self.sizeHint().height())

    def _browse(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "CA certificate", self.tls_ca.text(),
                                              "PEM certificates (*.pem *.crt);;All files (*)")
        if path:
            self.tls_ca.setText(path)

    def result_settings(self) -> ConnectionSettings:
        return ConnectionSettings(self.server.text().strip() or DEFAULT_SERVER,
                                  self.token.text().strip() or None,
                                  self.tls_ca.text().strip() or None,
                                  self.remember.isChecked())
