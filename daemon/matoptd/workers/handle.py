"""The daemon's handle on a worker: starting it, calling it, watching it, stopping it.

``Handle`` is what a lane needs of any worker; ``Worker`` is one as a local child process
(``python -m matoptd.workers.serve``) holding one end of a socket pair, and
``ray_cluster.RayWorker`` one as a Ray actor.
``call`` sends one engine call and waits for its answer, serving the blobs the worker fetches
meanwhile. Whatever ends the process, a signal (a segfault inside Mitsuba, kill -9, the
kernel's OOM killer), an exit, the memory limit or the watchdog, becomes ``WorkerLost`` with a
sentence that says what happened; the caller decides what that costs which job and starts a
fresh process. Nothing here imports Mitsuba or Dr.Jit.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Callable, Protocol

from matopt_api.costs import format_size

from .. import logs
from .devices import Placement, worker_environment

log = logging.getLogger("matoptd.workers")

START_TIMEOUT_S = 600.0  # importing Mitsuba and compiling the first kernels on a cold cache
STOP_TIMEOUT_S = 10.0


class WorkerLost(Exception):
    """The worker process ended or was stopped during a call. ``cause`` is "died" (signal or
    exit), "memory" (over its limit), "hung" (the watchdog), "stopped" (on purpose: a
    cancel inside a long render, the daemon shutting down) or "gone" (its machine left the
    Ray cluster); only "died" and "hung" count against the job that was running."""

    def __init__(self, reason: str, cause: str) -> None:
        super().__init__(reason)
        self.reason, self.cause = reason, cause


class CallFailed(Exception):
    """The engine raised: ``kind`` is "invalid" (the user's input), "memory", "engine" (a
    clear failure) or "internal" (a bug; the worker logged the traceback)."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


class Handle(Protocol):
    """A worker as its lane, the monitor and the listing see it."""

    name: str
    placement: Placement
    memory_limit: int
    state: str       # starting, idle, busy, restarting, failed
    info: dict       # from the worker once started: variant, device, host, threads, ...
    restarts: int
    last_exit: str   # why it last stopped, in words
    node: str        # the Ray node it runs on ("" for a local process)
    gone: bool       # its node left the cluster: it is not restarted

    @property
    def pid(self) -> int: ...

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def kill(self, reason: str, cause: str) -> None: ...

    def memory(self) -> int: ...

    def check_memory(self) -> None: ...

    def call(self, method: str, *args: Any, timeout: float | None = None) -> Any: ...


@dataclass
class Worker:
    """One supervised renderer process and what the daemon knows about it."""

    name: str                 # "workers/0"
    placement: Placement
    variant: str              # the variant it must run
    data_dir: Path
    memory_limit: int         # bytes of resident memory
    fetch: Callable[[str], bytes]  # blob digest -> content, for the worker's fetches
    state: str = "starting"   # starting, idle, busy, restarting, failed
    info: dict = field(default_factory=dict)  # from the worker: variant, device, pid, ...
    restarts: int = 0
    last_exit: str = ""
    node: str = ""            # the Ray node it runs on ("" for a local process)
    gone: bool = False        # its node left the cluster: it is not restarted
    _proc: subprocess.Popen | None = None
    _conn: Connection | None = None
    _stopping: str = ""       # why we stopped it, when we did
    _stop_cause: str = ""
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def pid(self) -> int:
        return self._proc.pid if self._proc and self._proc.poll() is None else 0

    @property
    def cache(self) -> Path:
        return self.data_dir / "worker-cache"

    # -- life -------------------------------------------------------------------------------

    def start(self, timeout: float = START_TIMEOUT_S) -> None:
        """Starts the process and waits until it is ready; raises WorkerLost when it is not."""
        ours, theirs = socket.socketpair()
        p = self.placement
        command = [sys.executable, "-m", "matoptd.workers.serve", "--fd", str(theirs.fileno()),
                   "--parent", str(os.getpid()), "--cache", str(self.cache),
                   "--variant", self.variant, "--cores", ",".join(map(str, p.cores)),
                   "--threads", str(p.threads)]
        with self._lock:
            self._stopping = self._stop_cause = ""
            self._proc = subprocess.Popen(command, pass_fds=[theirs.fileno()],
                                          stdin=subprocess.DEVNULL,
                                          stderr=subprocess.PIPE if logs.as_json() else None,
                                          env=worker_environment(self.data_dir, p))
            if self._proc.stderr is not None:
                logs.relay(self._proc.stderr, "matoptd." + self.name.replace("/", "."))
            self._conn = Connection(ours.detach())
        theirs.close()
        began = time.monotonic()
        while not self._conn.poll(0.2):
            if self._proc.poll() is not None or time.monotonic() - began > timeout:
                if self._proc.poll() is None:
                    self.kill(f"did not start within {timeout:g} s", "hung")
                raise self._lost()
        try:
            message = self._conn.recv()
        except (EOFError, OSError):
            raise self._lost() from None
        if message[0] != "ready":
            self._proc.wait()
            self.state = "failed"
            self.last_exit = f"could not start: {message[1]}"
            raise WorkerLost(self.last_exit, "died")
        self.info = message[1]
        self.state = "idle"
        log.info("%s ready in %.1f s: %s on %s (pid %d)", self.name, self.info["seconds"],
                 self.info["variant"], self.info["device"], self.pid)

    def stop(self) -> None:
        """Asks the process to exit; SIGKILL if it does not in time."""
        with self._lock:
            proc, conn = self._proc, self._conn
        if proc is None or proc.poll() is not None:
            return
        self._stopping, self._stop_cause = "was stopped with the daemon", "stopped"
        try:
            conn.send(("exit",))
            proc.wait(STOP_TIMEOUT_S)
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait()

    def kill(self, reason: str, cause: str) -> None:
        """SIGKILL, remembering why (``reason`` completes "the renderer process ..."): the call
        in progress then raises WorkerLost(reason)."""
        with self._lock:
            if self._proc is None or self._proc.poll() is not None or self._stopping:
                return
            self._stopping, self._stop_cause = reason, cause
            self._proc.kill()
        log.warning("%s (pid %d) stopped: %s", self.name, self._proc.pid, reason)

    def memory(self) -> int:
        """Resident memory of the process in bytes (0 when none runs)."""
        pid = self.pid
        if not pid:
            return 0
        try:
            with open(f"/proc/{pid}/status") as f:
                for line in f:
                    if line.startswith("VmRSS:"):
                        return int(line.split()[1]) * 1024
        except OSError:
            pass
        return 0

    def check_memory(self) -> None:
        """Stops the worker when it holds more than its limit: one job's render must not take
        the machine (and everybody's jobs) down with it."""
        used = self.memory()
        if used > self.memory_limit:
            self.kill(f"was stopped: its memory ({format_size(used)}) exceeded the worker "
                      f"memory limit of {format_size(self.memory_limit)}", "memory")

    # -- calls ------------------------------------------------------------------------------

    def call(self, method: str, *args: Any, timeout: float | None = None) -> Any:
        """One engine call. Raises CallFailed when the engine raised, WorkerLost when the
        process ended or did not answer within ``timeout`` seconds (then it is killed)."""
        conn = self._conn
        if conn is None or self.state in ("restarting", "failed"):
            raise WorkerLost(f"{self.name} is not running", "died")
        self.state = "busy"
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            conn.send(("call", method, args))
            while True:
                if not conn.poll(0.25):
                    if self._exited():
                        raise self._lost()
                    if deadline is not None and time.monotonic() > deadline:
                        self.kill(f"stopped answering: no reply to '{method}' in "
                                  f"{timeout:.0f} s", "hung")
                    continue
                message = conn.recv()
                if message[0] == "fetch":
                    self._serve_blob(conn, message[1])
                elif message[0] == "ok":
                    return message[1]
                else:
                    raise CallFailed(message[1], message[2])
        except (EOFError, OSError):
            raise self._lost() from None
        finally:
            if self.state == "busy":
                self.state = "idle"

    def _serve_blob(self, conn: Connection, sha256: str) -> None:
        try:
            data = self.fetch(sha256)
        except Exception as exc:  # noqa: BLE001 - the worker reports it as the job's input
            conn.send(("missing", f"blob {sha256} is not available: {exc}"))
        else:
            conn.send(("blob", data))

    def _exited(self) -> bool:
        return self._proc is None or self._proc.poll() is not None

    def _lost(self) -> WorkerLost:
        """What ended the process, once it has ended."""
        proc = self._proc
        try:
            code = proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
        if self._stopping:
            reason, cause = self._stopping, self._stop_cause
        else:
            reason, cause = describe_exit(code), "died"
        self.state, self.last_exit = "restarting", reason
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        return WorkerLost(reason, cause)


def describe_exit(code: int) -> str:
    """'died with SIGSEGV', 'exited with status 1'."""
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        extra = (" (killed from outside: by a user, or the kernel's out-of-memory killer)"
                 if -code == signal.SIGKILL else "")
        return f"died with {name}{extra}"
    return f"exited with status {code}"

