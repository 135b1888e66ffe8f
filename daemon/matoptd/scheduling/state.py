"""What job control, the lanes, recovery and the monitor share: the scheduler (who runs what,
and each active job's record), the store (what survives), the watchers, the clock, and one lock
over all of them. Everything here is injected, so tests run it with a fake clock, a fake
store and no threads.

``JobStore`` is what scheduling needs of a store, no more: ``store.Store`` is one, and the
unit tests have one in memory.
"""

from __future__ import annotations

import threading
import time
from typing import Iterable, Protocol

from ..engine_api import IterationRecord
from ..errors import NotFound
from ..records import JobRecord, Phase, ResultRecord, SceneRecord
from ..workers.handle import Handle
from .events import Events
from .scheduler import Scheduler


class Clock(Protocol):
    """Monotonic seconds for decisions, wall-clock seconds for what records show (the
    ``time`` module is one)."""

    def monotonic(self) -> float: ...

    def time(self) -> float: ...


class BlobWriter(Protocol):
    def put(self, data: bytes, owner: str) -> str: ...


class CheckpointFiles(Protocol):
    def write(self, job: str, data: bytes) -> None: ...

    def read(self, job: str) -> bytes | None: ...

    def exists(self, job: str) -> bool: ...

    def size(self, job: str) -> int: ...


class DiskState(Protocol):
    full_since: float | None

    def space_back(self, held: int = 0) -> bool: ...


class JobStore(Protocol):
    blobs: BlobWriter
    checkpoints: CheckpointFiles
    disk: DiskState

    def add_job(self, job: JobRecord, request_id: str | None) -> None: ...

    def put_job(self, job: JobRecord) -> None: ...

    def get_job(self, name: str, owner: str | None = None) -> JobRecord: ...

    def list_jobs(self, owner: str | None, offset: int = 0, limit: int = -1,
                  phases: Iterable[Phase] = ()) -> list[JobRecord]: ...

    def delete_job(self, name: str) -> None: ...

    def add_iterations(self, job: str, records: list[IterationRecord]) -> None: ...

    def history(self, job: str, offset: int = 0, limit: int = -1
                ) -> list[IterationRecord]: ...

    def truncate_history(self, job: str, keep_below: int) -> None: ...

    def put_result(self, result: ResultRecord) -> None: ...

    def get_scene(self, owner: str, name: str) -> SceneRecord: ...


class State:
    def __init__(self, store: JobStore, scheduler: Scheduler, events: Events | None = None,
                 clock: Clock = time) -> None:
        self.store, self.scheduler = store, scheduler
        self.events = events or Events()
        self.clock = clock
        self.workers: dict[str, Handle] = {}  # replaced whole, never changed in place
        self.lock = threading.RLock()
        self.wake = threading.Condition(self.lock)
        self.stop_asked: float | None = None  # clock.monotonic() when the daemon began to stop
        self.stopped = threading.Event()  # set with ``stop_asked``: cuts waits short
        # Seconds a lane leaves the CPU to the server when a client waits on a job (its load,
        # its first iteration): beside CPU workers the server runs niced below them and would
        # answer only when the worker next pauses (main.py sets it; 0: it need not).
        self.server_turn = 0.0

    @property
    def stopping(self) -> bool:
        return self.stop_asked is not None

    def record(self, name: str, owner: str | None = None) -> JobRecord:
        """The job's record: the scheduler's while it holds the job (the one that changes),
        else a copy of the store's (the scheduler may take it up and change it). With
        ``owner``, another user's job is NOT_FOUND, as if absent."""
        job = self.scheduler.jobs.get(name)
        if job is None:
            return self.store.get_job(name, owner).snapshot()
        if owner is not None and job.user != owner:
            raise NotFound(f"job '{name}' not found")
        return job.record

    def save(self, record: JobRecord) -> None:
        """Persists the record as it stands and tells its watchers."""
        record.updated = self.clock.time()
        self.store.put_job(record)
        self.events.publish(record.name, [record.snapshot()])

    def notify(self) -> None:
        """Wakes the lanes: there may be something to do."""
        with self.lock:
            self.wake.notify_all()
