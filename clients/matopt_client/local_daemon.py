"""A private matoptd in a child process, for when no daemon is running (``matopt demo``).

The daemon runs as ``python -m matoptd`` in its own process: the client process itself never
imports mitsuba or drjit, and the renderer's memory goes away with the child.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

from matopt_client.client import Client, ClientError, Unreachable, connect

START_TIMEOUT_S = 120.0  # importing mitsuba and picking a variant can take a while on first use
STOP_TIMEOUT_S = 15.0


class LocalDaemon:
    """Starts matoptd on a free localhost port with a throwaway data directory.

    Use as a context manager: the daemon is stopped (SIGTERM, then SIGKILL) and its directory
    removed on the way out, also on errors and Ctrl-C, so no renderer is left running.
    """

    def __init__(self, start_timeout: float = START_TIMEOUT_S) -> None:
        self.start_timeout = start_timeout
        self.directory = Path(tempfile.mkdtemp(prefix="matoptd-"))
        self.log_path = self.directory / "matoptd.log"
        self.process: subprocess.Popen | None = None
        self.address: str | None = None

    def start(self, on_wait: Callable[[float], None] | None = None) -> Client:
        """Starts the daemon and returns a client once it answers.

        ``on_wait(seconds_so_far)`` is called while waiting, for a progress message.
        """
        port_file = self.directory / "port"
        data_dir = self.directory / "data"
        # One worker: a private daemon serves one command's jobs one at a time, and on a GPU
        # each further worker would spend its own CUDA start before the daemon answers.
        command = [sys.executable, "-m", "matoptd", "--listen", "127.0.0.1:0",
                   "--data-dir", str(data_dir), "--port-file", str(port_file),
                   "--workers-per-device", "1"]
        with open(self.log_path, "wb") as log:
            self.process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=log,
                                            stderr=subprocess.STDOUT,
                                            start_new_session=True)  # Ctrl-C is ours to handle
        started = time.monotonic()
        while True:
            waited = time.monotonic() - started
            if on_wait:
                on_wait(waited)
            if self.process.poll() is not None:
                raise ClientError(f"the private matoptd exited with status "
                                  f"{self.process.returncode}: {self.log_tail()}")
            if waited > self.start_timeout:
                raise ClientError(f"the private matoptd did not answer within "
                                  f"{self.start_timeout:g} s: {self.log_tail()}")
            port = _read_port(port_file)
            if port:
                self.address = f"127.0.0.1:{port}"
                try:
                    return connect(self.address, probe_timeout=2.0)
                except Unreachable:
                    pass
            time.sleep(0.25)

    def log_tail(self, lines: int = 3) -> str:
        """The end of the daemon's output, folded into one line, to explain a failed start."""
        try:
            text = self.log_path.read_text(errors="replace").strip().splitlines()
        except OSError:
            return "(no output)"
        return " | ".join(text[-lines:]) or "(no output)"

    def stop(self) -> None:
        """SIGTERM lets the daemon checkpoint and exit; SIGKILL if it does not in time."""
        process, self.process = self.process, None
        if process is not None and process.poll() is None:
            try:
                process.send_signal(signal.SIGTERM)
                process.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            except KeyboardInterrupt:  # a second Ctrl-C: do not wait any longer
                process.kill()
                process.wait()
                raise
        shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self) -> LocalDaemon:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _read_port(path: Path) -> int | None:
    """The port the daemon wrote, or None while the file is absent or still being written."""
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None
