"""A thread that watches what no lane can see from inside a call: workers over their memory
limit, a cancel or a shutdown that an iteration in flight keeps waiting, and the disk's space
coming back after it filled up. It keeps normal priority where the server is niced below the
workers (main.py): its kills must not wait behind the render they stop."""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

from ..errors import DiskFull
from .recovery import Recovery
from .state import State

log = logging.getLogger("matoptd.monitor")

PERIOD_S = 0.1
CANCEL_GRACE_S = 3.0  # a cancel inside a long iteration stops the worker after this
SHUTDOWN_GRACE_S = 10.0  # on shutdown, an iteration running longer is cut off


class Monitor:
    def __init__(self, state: State, recovery: Recovery, lanes_alive: Callable[[], bool]
                 ) -> None:
        self.state, self.recovery, self._lanes_alive = state, recovery, lanes_alive
        self.thread = threading.Thread(target=self._run, name="matoptd-monitor", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        while not (self.state.stopping and not self._lanes_alive()):
            try:
                self.check()
            except Exception:  # noqa: BLE001 - a shutdown waits on it to cut iterations off
                log.exception("the monitor's check failed")
            time.sleep(PERIOD_S)

    def check(self) -> None:
        """One look at everything."""
        state = self.state
        disk = state.store.disk
        with state.lock:
            late = state.scheduler.late_cancels(CANCEL_GRACE_S)
            held = state.scheduler.held
            jobs = list(state.scheduler.jobs) if held or disk.full_since is not None else []
        workers = state.workers
        for w in workers.values():
            if w.state == "busy":
                w.check_memory()
        # What the held jobs write next: their checkpoints again (beside the ones they replace).
        need = sum(state.store.checkpoints.size(name) for name in jobs)
        if (held or disk.full_since is not None) and disk.space_back(need) and held:
            log.info("space on the data directory's disk again: jobs go on")
            try:
                self.recovery.unhold()
            except DiskFull:
                pass  # filled up again meanwhile
        for name in late:
            if name in workers:
                workers[name].kill("was stopped: its job was cancelled during a long "
                                   "iteration", "stopped")
        asked = state.stop_asked
        if asked is not None and state.clock.monotonic() - asked > SHUTDOWN_GRACE_S:
            for w in workers.values():
                if w.state == "busy":
                    w.kill("was stopped: the daemon shut down during a long iteration",
                           "stopped")
