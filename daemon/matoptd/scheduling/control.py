"""What the API asks of jobs: create, pause, resume, cancel, delete. Each changes the job's
phase through the scheduler, persists its record and returns it: nothing here waits on a
worker (a pause or a cancel of a loaded job is carried out at its next iteration boundary)."""

from __future__ import annotations

import logging

from ..errors import FailedPrecondition
from ..logs import about
from ..records import RESUME_PENDING, JobRecord, Phase
from .recovery import Recovery
from .state import State

log = logging.getLogger("matoptd.control")


class JobControl:
    def __init__(self, state: State, recovery: Recovery) -> None:
        self.state, self.recovery = state, recovery
        self.scheduler, self.store = state.scheduler, state.store

    def create(self, record: JobRecord, request_id: str | None) -> JobRecord:
        """A new job, QUEUED. Like the others, returns a snapshot of the record (the lanes
        change the record itself)."""
        with self.state.lock:
            record.created = record.updated = self.state.clock.time()
            self.store.add_job(record, request_id)
            self.scheduler.add_job(record)
            self.state.wake.notify_all()
            snapshot = record.snapshot()
        self.recovery.note_waiting()
        return snapshot

    def pause(self, owner: str, name: str) -> JobRecord:
        log.info("%s: pause requested by %s", name, owner, extra=about(name, owner))
        with self.state.lock:
            record = self.state.record(name, owner)
            if record.phase in (Phase.QUEUED, Phase.RUNNING):
                self.scheduler.pause(name)
                self.state.save(record)
                self.state.wake.notify_all()
            elif not record.phase.active and record.phase is not Phase.PAUSED:
                raise FailedPrecondition(f"job '{name}' is {record.phase.state}: only a "
                                         "queued or running job can be paused")
            return record.snapshot()

    def resume(self, owner: str, name: str) -> JobRecord:
        """A paused or interrupted job queues again (from its checkpoint); a pause that was
        not carried out yet is withdrawn."""
        log.info("%s: resume requested by %s", name, owner, extra=about(name, owner))
        with self.state.lock:
            record = self.state.record(name, owner)
            if record.phase is Phase.PAUSING:
                self.scheduler.resume(name)
                self.state.save(record)
            elif record.phase in (Phase.PAUSED, Phase.INTERRUPTED):
                self._hold(record)
                self.scheduler.resume(name)
                record.resumed_from = RESUME_PENDING  # the load says from where
                self.state.save(record)
                self.state.wake.notify_all()
            elif not record.phase.active:
                raise FailedPrecondition(f"job '{name}' is {record.phase.state}: only a "
                                         "paused or interrupted job can be resumed")
            return record.snapshot()

    def cancel(self, owner: str, name: str) -> JobRecord:
        """A job that never ran ends CANCELLED now; any other stops at its next iteration
        boundary (loaded again if need be) and renders its results first."""
        log.info("%s: cancel requested by %s", name, owner, extra=about(name, owner))
        with self.state.lock:
            record = self.state.record(name, owner)
            if record.phase.final:
                raise FailedPrecondition(f"job '{name}' already ended ({record.phase.state})")
            self._hold(record)  # paused or interrupted, not loaded
            self.scheduler.cancel(name)
            self.state.save(record)
            self.state.wake.notify_all()
            return record.snapshot()

    def delete(self, owner: str, name: str) -> None:
        with self.state.lock:
            record = self.state.record(name, owner)
            job = self.scheduler.jobs.get(name)
            if record.phase in (Phase.RUNNING, Phase.PAUSING, Phase.CANCELLING,
                                Phase.ENDING) or (job and (job.busy or job.worker)):
                raise FailedPrecondition(f"job '{name}' is {record.phase.state}: cancel it "
                                         "before deleting it")
            self.scheduler.remove(name)
            self.store.delete_job(name)

    def _hold(self, record: JobRecord) -> None:
        """The scheduler holds the job (a paused or interrupted one may not be held)."""
        if record.name not in self.scheduler.jobs:
            self.scheduler.add_job(record,
                                   started=self.store.checkpoints.exists(record.name))

