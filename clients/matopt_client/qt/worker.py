"""Network work off the GUI thread: one-shot calls on a thread pool, and job watch streams.

Every gRPC call can take as long as the server or the network makes it take (a daemon under
load, a laptop that lost Wi-Fi). Run on the GUI thread, a call would freeze the window exactly
when the user most needs it to say what is wrong, so the window never calls the API itself:
it hands a function to :class:`Tasks` and gets the result (or the exception) back on the GUI
thread, and follows a running job through a :class:`JobWatcher` thread.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from typing import Any, Callable

import grpc
from PySide6.QtCore import QObject, QRunnable, QThread, QThreadPool, Qt, Signal, Slot

from matopt_client import client as mc
from matopt_api.v1 import matopt_pb2 as pb

log = logging.getLogger(__name__)

Done = Callable[[Any], None]
Failed = Callable[[BaseException], None]

# Unary calls get a deadline so that a daemon that stopped answering (but still holds the
# TCP connection) shows up as an error instead of a call that never returns.
CALL_TIMEOUT_S = 30.0
# A paused job's standard errors on request wait for a worker's turn, then take up to a minute.
ESTIMATE_TIMEOUT_S = 600.0


class _Call(QRunnable):
    """Runs one function on a pool thread and reports back through the owning :class:`Tasks`."""

    def __init__(self, tasks: Tasks, ident: int, fn: Callable[[], Any]) -> None:
        super().__init__()
        self._tasks, self._ident, self._fn = tasks, ident, fn
        self.setAutoDelete(True)

    def run(self) -> None:
        try:
            outcome = (self._fn(), None)
        except BaseException as exc:  # noqa: BLE001 - every failure must reach the GUI
            outcome = (None, exc)
        try:
            self._tasks._finished.emit(self._ident, *outcome)
        except RuntimeError:  # the window (and its Tasks) is gone: nobody is waiting
            pass


class Tasks(QObject):
    """A thread pool whose results come back as calls on the GUI thread.

    The callbacks are kept here, keyed by a number, and invoked by a slot of this object,
    which lives on the GUI thread; the signal that carries the number is always queued. So a
    callback never runs on a pool thread, whatever kind of callable it is.
    """

    _finished = Signal(int, object, object)  # ident, result, exception

    def __init__(self, parent: QObject | None = None, max_threads: int = 4) -> None:
        super().__init__(parent)
        self._pool = QThreadPool(self)
        self._pool.setMaxThreadCount(max_threads)
        self._ids = itertools.count(1)
        # ident -> (on_done, on_error, what, since when (monotonic))
        self._pending: dict[int, tuple[Done | None, Failed | None, str, float]] = {}
        self._closed = False
        self._finished.connect(self._deliver, Qt.ConnectionType.QueuedConnection)

    def submit(self, fn: Callable[[], Any], on_done: Done | None = None,
               on_error: Failed | None = None, what: str = "a call") -> int:
        """Runs ``fn()`` on a pool thread; then ``on_done(result)`` or ``on_error(exc)`` here.

        ``what`` names the call in :meth:`pending`, for logs and for tests that wait on it.
        """
        if self._closed:
            return 0
        ident = next(self._ids)
        self._pending[ident] = (on_done, on_error, what, time.monotonic())
        self._pool.start(_Call(self, ident, fn))
        return ident

    def busy(self) -> int:
        """How many submitted calls have not delivered their outcome yet (tests wait on 0)."""
        return len(self._pending)

    def pending(self) -> list[str]:
        """What the calls still under way are doing and for how long, oldest first."""
        now = time.monotonic()
        return [f"{what} ({now - since:.1f} s)"
                for _, _, what, since in (self._pending[i] for i in sorted(self._pending))]

    @Slot(int, object, object)
    def _deliver(self, ident: int, result: Any, exc: BaseException | None) -> None:
        on_done, on_error, _, _ = self._pending.pop(ident, (None, None, "", 0.0))
        if self._closed:
            return
        if exc is None:
            if on_done is not None:
                on_done(result)
        elif on_error is not None:
            on_error(exc)
        else:
            log.error("background call failed: %s", describe(exc))

    def shutdown(self, wait_ms: int = 5000) -> None:
        """Drops queued calls and waits (bounded) for running ones; no callback runs after."""
        self._closed = True
        self._pool.clear()
        self._pool.waitForDone(wait_ms)


def describe(exc: BaseException) -> str:
    """One line for the user, whatever was raised: gRPC status, client error or a bug."""
    if isinstance(exc, grpc.RpcError):
        return mc.error_message(exc)
    if isinstance(exc, mc.ClientError):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"


class JobWatcher(QThread):
    """Follows one job's WatchJob stream on its own thread.

    ``event`` carries every JobEvent; when the stream ends without a final state (the daemon
    stopped, which leaves the job INTERRUPTED) the job is fetched once more so the window does
    not keep showing a stale RUNNING. ``failed`` carries the exception that broke the stream,
    unless :meth:`stop` asked for it. Each signal carries the watcher's ``generation`` so the
    window can drop events still queued from a watcher it has already replaced.
    """

    event = Signal(int, object)   # generation, pb.JobEvent
    failed = Signal(int, object)  # generation, exception
    ended = Signal(int)           # generation; after the last event

    def __init__(self, client: mc.Client, job_name: str, generation: int,
                 parent: QObject | None = None) -> None:
        super().__init__(parent)
        self.client, self.job_name, self.generation = client, job_name, generation
        self._lock = threading.Lock()
        self._call: grpc.Future | None = None
        self._stopped = False

    def run(self) -> None:
        try:
            call = self.client.jobs.WatchJob(pb.WatchJobRequest(name=self.job_name))
            with self._lock:
                self._call = call
                if self._stopped:
                    call.cancel()
            last: pb.Job | None = None
            for event in call:
                self.event.emit(self.generation, event)
                if event.HasField("job"):
                    last = event.job
            if not self._stopped and (last is None or last.state not in mc.TERMINAL_STATES):
                job = self.client.jobs.GetJob(pb.GetJobRequest(name=self.job_name),
                                              timeout=CALL_TIMEOUT_S)
                self.event.emit(self.generation, pb.JobEvent(job=job))
        except BaseException as exc:  # noqa: BLE001 - reported to the window, never lost
            if not self._stopped:
                self.failed.emit(self.generation, exc)
        finally:
            self.ended.emit(self.generation)

    def stop(self, wait_ms: int = 3000) -> None:
        """Cancels the stream (the daemon unsubscribes at once) and waits for the thread."""
        with self._lock:
            self._stopped = True
            if self._call is not None:
                self._call.cancel()
        self.wait(wait_ms)
