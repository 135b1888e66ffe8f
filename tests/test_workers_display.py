"""The daemon's renderer workers as users see them: ``matopt info`` and the Qt status bar.

No daemon: ServerInfo messages are built by hand (and, for the window, answered by a fake
client), so these tests check the wording and the refresh logic, not the daemon.
"""

from __future__ import annotations

import json
import logging
import os
import threading

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import grpc
import pytest
from click.testing import CliRunner

import matopt_client.cli as cli_module
from matopt_client import client as mc
from matopt_client import workers as wk
from matopt_api.v1 import matopt_pb2 as pb

MiB, GiB = 1024**2, 1024**3
SIGKILL_EXIT = "killed by SIGKILL during jobs/ab12"


def busy_cpu_worker() -> pb.Worker:
    """Runs one of the caller's jobs and two of other users' jobs; restarted once."""
    return pb.Worker(name="workers/0", state=pb.WORKER_STATE_BUSY, variant="llvm_ad_rgb",
                     device="CPU: 2 threads (cores 0-1)", host="box", pid=1234,
                     jobs=["jobs/ab12"], job_count=3, restarts=1, last_exit=SIGKILL_EXIT,
                     memory_bytes=312 * MiB, memory_limit_bytes=8 * GiB, threads=2)


def idle_cpu_worker() -> pb.Worker:
    return pb.Worker(name="workers/1", state=pb.WORKER_STATE_IDLE, variant="llvm_ad_rgb",
                     device="CPU: 4 threads (cores 2-5)", host="box", pid=1300,
                     memory_bytes=int(1.5 * GiB), memory_limit_bytes=8 * GiB, threads=4)


def server_info(*workers: pb.Worker) -> pb.ServerInfo:
    return pb.ServerInfo(version="0.1.0", variant="llvm_ad_rgb", device="CPU", user="alice",
                         losses=["l2"], integrators=["prb"], capabilities=["bundles"],
                         workers=list(workers))


# =============================================================================================
# Wording of one worker and of the summary
# =============================================================================================


def test_one_busy_worker_reads_as_the_cli_prints_it():
    [line] = wk.worker_lines([busy_cpu_worker()], "llvm_ad_rgb")
    assert line == ("workers/0  busy  CPU: 2 threads (cores 0-1)  pid 1234 @ box  "
                    "312 MiB of 8.0 GiB  3 jobs (yours: jobs/ab12)  "
                    f"restarts 1 (last: {SIGKILL_EXIT})")


def test_other_users_jobs_are_counted_never_named():
    worker = pb.Worker(name="workers/0", state=pb.WORKER_STATE_BUSY, device="NVIDIA H100", pid=7,
                       host="gpu", job_count=2)
    [line] = wk.worker_lines([worker])
    assert "2 jobs" in line
    assert "yours" not in line and "jobs/" not in line
    one = pb.Worker(name="workers/0", state=pb.WORKER_STATE_IDLE, pid=7, job_count=1)
    assert wk.jobs_text(one) == "1 job"
    assert wk.jobs_text(pb.Worker(name="workers/0")) == "no jobs"


def test_lines_are_aligned_in_columns():
    restarting = pb.Worker(name="workers/10", state=pb.WORKER_STATE_RESTARTING, device="NVIDIA H100",
                           host="gpu", restarts=3, last_exit="exceeded 8.0 GiB")
    lines = wk.worker_lines([busy_cpu_worker(), restarting], "llvm_ad_rgb")
    assert lines[0].index("CPU: 2 threads") == lines[1].index("NVIDIA H100")
    assert lines[0].index("pid 1234") == lines[1].index("no process @ gpu")
    assert lines[1].split()[1] == "restarting"


def test_a_restarting_worker_shows_no_stale_process_or_memory():
    worker = pb.Worker(name="workers/1", state=pb.WORKER_STATE_RESTARTING, variant="cuda_ad_rgb",
                       device="NVIDIA H100 (CUDA device 0)", host="gpu", pid=0,
                       memory_bytes=5 * GiB, memory_limit_bytes=40 * GiB, restarts=2,
                       last_exit="exited with status 1")
    cells = wk.worker_cells(worker, "cuda_ad_rgb")
    assert cells[:4] == ["workers/1", "restarting", "NVIDIA H100 (CUDA device 0)",
                         "no process @ gpu"]
    assert cells[4] == ""  # no memory figure for a process that is gone
    assert cells[6] == "restarts 2 (last: exited with status 1)"


def test_a_failed_worker_says_why_even_without_restarts():
    worker = pb.Worker(name="workers/0", state=pb.WORKER_STATE_FAILED, device="NVIDIA H100",
                       last_exit="CUDA driver too old")
    cells = wk.worker_cells(worker)
    assert cells[1] == "failed"
    assert cells[6] == "(last: CUDA driver too old)"


def test_variant_shown_only_where_it_differs_and_threads_when_not_in_the_device():
    gpu = pb.Worker(name="workers/0", variant="cuda_ad_rgb", device="NVIDIA H100")
    cpu = pb.Worker(name="workers/1", variant="llvm_ad_rgb", device="CPU", threads=8)
    assert wk.device_text(gpu, "cuda_ad_rgb") == "NVIDIA H100"
    assert wk.device_text(cpu, "cuda_ad_rgb") == "CPU, 8 threads (llvm_ad_rgb)"
    assert wk.device_text(busy_cpu_worker(), "llvm_ad_rgb") == "CPU: 2 threads (cores 0-1)"


def test_memory_figures():
    assert wk.memory_size(312 * MiB) == "312 MiB"
    assert wk.memory_size(8 * GiB) == "8.0 GiB"
    assert wk.memory_size(int(1.5 * GiB)) == "1.5 GiB"
    no_limit = pb.Worker(pid=5, memory_bytes=700 * MiB)
    assert wk.memory_text(no_limit) == "700 MiB"
    unmeasured = pb.Worker(pid=5, memory_limit_bytes=16 * GiB)
    assert wk.memory_text(unmeasured) == "limit 16.0 GiB"


def test_summary_counts_each_state_in_words():
    idle = pb.Worker(state=pb.WORKER_STATE_IDLE)
    assert wk.summary([busy_cpu_worker(), idle]) == "2 workers: 1 busy, 1 idle"
    assert wk.summary([pb.Worker(state=pb.WORKER_STATE_FAILED), idle,
                       pb.Worker(state=pb.WORKER_STATE_RESTARTING), idle]) \
        == "4 workers: 2 idle, 1 restarting, 1 failed"
    assert wk.summary([pb.Worker(state=pb.WORKER_STATE_STARTING)]) == "1 worker: 1 starting"
    assert wk.summary([]) == "no workers"
    assert wk.state_word(99) == "unknown"  # a state a newer daemon may add


# =============================================================================================
# matopt info
# =============================================================================================


class FakeCliClient:
    """What ``matopt info`` uses of a connected client."""

    def __init__(self, info: pb.ServerInfo) -> None:
        self.info, self.target = info, "box:50051"


def run_info(monkeypatch, info: pb.ServerInfo, *args: str):
    monkeypatch.setattr(cli_module, "connected", lambda: FakeCliClient(info))
    return CliRunner().invoke(cli_module.cli, ["info", *args])


def test_matopt_info_lists_the_workers(monkeypatch):
    info = server_info(busy_cpu_worker(), idle_cpu_worker())
    result = run_info(monkeypatch, info)
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    summary = [line for line in lines if line.startswith("workers:")]
    assert summary and summary[0].split(None, 1)[1] == "2 workers: 1 busy, 1 idle"
    start = lines.index(summary[0]) + 1
    assert lines[start:start + 2] == [
        "  workers/0  busy  CPU: 2 threads (cores 0-1)  pid 1234 @ box  312 MiB of 8.0 GiB  "
        f"3 jobs (yours: jobs/ab12)  restarts 1 (last: {SIGKILL_EXIT})",
        "  workers/1  idle  CPU: 4 threads (cores 2-5)  pid 1300 @ box  1.5 GiB of 8.0 GiB  "
        "no jobs",
    ]
    # The other fields are still there, aligned with the workers' summary.
    assert any(line.startswith("user:") and line.endswith(" alice") for line in lines)
    assert len({line.index(line.split(":", 1)[1].strip()) for line in lines
                if not line.startswith("  ")}) == 1


def test_matopt_info_json_has_the_workers(monkeypatch):
    result = run_info(monkeypatch, server_info(busy_cpu_worker()), "--json")
    assert result.exit_code == 0, result.output
    [worker] = json.loads(result.output)["workers"]
    assert worker["name"] == "workers/0"
    assert worker["state"] == "WORKER_STATE_BUSY"
    assert worker["jobs"] == ["jobs/ab12"]
    assert int(worker["memoryBytes"]) == 312 * MiB
    assert worker["lastExit"] == SIGKILL_EXIT


def test_matopt_info_from_a_daemon_without_workers_says_nothing_about_them(monkeypatch):
    result = run_info(monkeypatch, server_info())
    assert result.exit_code == 0, result.output
    assert "worker" not in result.output


# =============================================================================================
# Qt: the status bar label, and its refresh through the connection's probe
# =============================================================================================

pytest.importorskip("PySide6.QtWidgets", reason="PySide6 is not installed")
pytest.importorskip("pytestqt", reason="pytest-qt is not installed")

from matopt_client.qt import pyside_check  # noqa: E402

QT_BROKEN = pyside_check.none_refcount_bug()
needs_qt = pytest.mark.skipif(QT_BROKEN, reason=pyside_check.problem() or "broken PySide6")


def plain(html_text: str) -> str:
    """What a tooltip shows, as text."""
    from PySide6.QtGui import QTextDocument
    document = QTextDocument()
    document.setHtml(html_text)
    return document.toPlainText()


@needs_qt
def test_status_label_and_tooltip(qtbot):
    from matopt_client.qt.workers_label import WorkersLabel

    label = WorkersLabel()
    qtbot.addWidget(label)
    assert label.isHidden() and label.text() == ""  # nothing known before connecting

    label.set_info(server_info(busy_cpu_worker(), idle_cpu_worker()))
    assert not label.isHidden()
    assert label.text() == "2 workers: 1 busy, 1 idle"
    tip = plain(label.toolTip())
    assert tip.splitlines()[0] == "2 workers: 1 busy, 1 idle"
    assert "workers/0 busy" in tip.splitlines() and "workers/1 idle" in tip.splitlines()
    for cell in wk.worker_cells(busy_cpu_worker(), "llvm_ad_rgb") + \
            wk.worker_cells(idle_cpu_worker(), "llvm_ad_rgb"):
        assert cell in tip
    assert "312 MiB of 8.0 GiB" in tip and "yours: jobs/ab12" in tip
    assert "WORKER_" not in label.text() + tip  # words, not enum names
    assert label.styleSheet() == ""

    restarting = idle_cpu_worker()
    restarting.state, restarting.pid = pb.WORKER_STATE_RESTARTING, 0
    label.set_info(server_info(busy_cpu_worker(), restarting))
    assert label.text() == "2 workers: 1 busy, 1 restarting"
    assert "color" in label.styleSheet()  # trouble stands out
    assert "no process @ box" in plain(label.toolTip())

    label.set_info(None)  # connection lost: no stale states
    assert label.isHidden() and label.text() == "" and label.toolTip() == ""
    label.set_info(server_info())  # a daemon older than the workers list
    assert label.isHidden()


class Unavailable(grpc.RpcError):
    def code(self) -> grpc.StatusCode:
        return grpc.StatusCode.UNAVAILABLE

    def details(self) -> str:
        return "connection refused"


class FakeDaemon:
    """Answers GetServerInfo (and an empty ListJobs) on the window's worker threads; ``info``
    and ``down`` are changed by the test."""

    def __init__(self, info: pb.ServerInfo) -> None:
        self.lock = threading.Lock()
        self.info, self.down, self.probes = info, False, 0

    def answer(self) -> pb.ServerInfo:
        with self.lock:
            self.probes += 1
            if self.down:
                raise Unavailable()
            return self.info

    def client(self, settings) -> "FakeQtClient":
        if self.down:
            raise mc.Unreachable(f"cannot reach matoptd at {settings.server}")
        return FakeQtClient(self)


class FakeQtClient:
    def __init__(self, daemon: FakeDaemon) -> None:
        self.target, self.info = "fake:1", daemon.answer()
        self.server = self.jobs = self
        self.daemon = daemon

    def GetServerInfo(self, request, timeout=None):  # noqa: N802 - the stub's name
        return self.daemon.answer()

    def ListJobs(self, request, timeout=None):  # noqa: N802
        return pb.ListJobsResponse()

    def close(self) -> None:
        pass


@needs_qt
def test_window_refreshes_workers_and_a_lost_daemon_is_one_banner(qtbot, tmp_path,
                                                                  monkeypatch, caplog):
    from PySide6.QtCore import QSettings

    from matopt_client.qt import connection as qt_connection
    from matopt_client.qt.app import MainWindow
    from matopt_client.qt.connection import ConnectionSettings, SettingsStore

    daemon = FakeDaemon(server_info(busy_cpu_worker(), idle_cpu_worker()))
    monkeypatch.setattr(qt_connection, "_connect", daemon.client)
    store = SettingsStore(QSettings(str(tmp_path / "settings.ini"), QSettings.Format.IniFormat))
    window = MainWindow(store, tmp_path / "cache", probe_interval_s=0.1, retry_interval_s=0.1,
                        jobs_refresh_s=3600, preview_interval_s=3600)
    qtbot.addWidget(window)
    window.show()
    label = window.workers_label
    try:
        assert label.isHidden()
        window.connect_to(ConnectionSettings("fake:1"), save=False)
        qtbot.waitUntil(lambda: label.text() == "2 workers: 1 busy, 1 idle", timeout=5000)
        assert label.isVisible()
        assert "yours: jobs/ab12" in plain(label.toolTip())

        # The probe refreshes the label without any action of the user.
        restarting = idle_cpu_worker()
        restarting.state, restarting.pid, restarting.restarts = pb.WORKER_STATE_RESTARTING, 0, 1
        with daemon.lock:
            daemon.info = server_info(busy_cpu_worker(), restarting)
        qtbot.waitUntil(lambda: label.text() == "2 workers: 1 busy, 1 restarting", timeout=5000)

        # The daemon goes away: one banner, one log line, however many retries fail; the
        # label hides instead of showing stale states.
        caplog.set_level(logging.WARNING, logger="matopt_client.qt.connection")
        with daemon.lock:
            daemon.down = True
        qtbot.waitUntil(lambda: window.connection.lost_message is not None, timeout=5000)
        assert label.isHidden()
        probes = daemon.probes
        qtbot.wait(600)  # several retry intervals
        assert window.banner.text().startswith("lost connection to matoptd at fake:1")
        assert window.banner.text().count("lost connection") == 1
        assert len([r for r in caplog.records if "lost connection" in r.getMessage()]) == 1
        assert daemon.probes == probes  # retries reconnect; they do not probe a dead client

        # Back: the label returns with the daemon's current answer.
        with daemon.lock:
            daemon.down = False
            daemon.info = server_info(idle_cpu_worker())
        qtbot.waitUntil(lambda: label.text() == "1 worker: 1 idle", timeout=5000)
        assert window.banner.text() == ""
    finally:
        window.shutdown()
