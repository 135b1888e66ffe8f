"""What the daemon does when things go wrong: it restarted (jobs that were running are
INTERRUPTED, queued ones queue again), it stops (running jobs are INTERRUPTED), a worker was
lost (the job it ran is retried once from its checkpoint, or failed with a message saying what
happened; the jobs it held reload elsewhere; a fresh process takes its place), a worker's node
left, or the disk is full (jobs are held, nothing is lost)."""

from __future__ import annotations

import logging

from ..errors import NotFound, UserError
from ..records import ACTIVE, JobRecord, Phase, RESUME_PENDING
from ..store.outputs import results_from_history
from ..workers.client import EngineClient
from ..workers.handle import Handle, WorkerLost
from .scheduler import INTERRUPTIBLE, Action
from .state import State

log = logging.getLogger("matoptd.recovery")

RESTART_DELAYS_S = (0.0, 1.0, 5.0, 30.0)  # between failed restarts of a worker
DOING = {"load": "loading the job", "evict": "saving the job's checkpoint",
         "park": "pausing the job", "cancel": "stopping the job",
         "results": "rendering the job's result images",
         "estimate": "estimating the job's standard errors", "finish": "making the job's results",
         "task": "a task"}
WAITING = ("waiting: no renderer worker is available (every worker's machine has left, or "
           "none has joined yet); the job runs when one joins")


class Recovery:
    def __init__(self, state: State, watchdog: float) -> None:
        self.state, self.watchdog = state, watchdog
        self.scheduler, self.store = state.scheduler, state.store

    # -- the daemon's restarts --------------------------------------------------------------

    def recover(self) -> None:
        """After a restart: jobs that were running when the daemon stopped are INTERRUPTED
        (ResumeJob continues them); queued ones run again."""
        with self.state.lock:
            for record in self.store.list_jobs(None, phases=ACTIVE):
                if record.phase is Phase.QUEUED:
                    self.scheduler.add_job(record,
                                           started=self.store.checkpoints.exists(record.name))
                else:
                    self.scheduler.interrupt(record, "the daemon stopped while the job ran")
                    self.state.save(record)

    def interrupt_all(self, why: str) -> None:
        """The daemon stops: jobs that have been running are INTERRUPTED."""
        with self.state.lock:
            for job in list(self.scheduler.jobs.values()):
                if job.phase in INTERRUPTIBLE:
                    self.scheduler.interrupt(job.record, why)
                    self.state.save(job.record)

    # -- a lost worker ----------------------------------------------------------------------

    def settle(self, w: Handle, action: Action, lost: WorkerLost) -> None:
        """What the loss of a worker costs: the job it ran (retried once from its checkpoint,
        or failed with what happened) and the jobs it held (reloaded elsewhere)."""
        with self.state.lock:
            job = self.scheduler.jobs.get(action.job)
            running = job.record if job is not None else None
            what = lost.reason
            if running is not None:
                what += (f" during iteration {running.iteration}" if action.kind == "step"
                         else f" while {DOING[action.kind]}")
            cancelling = running is not None and running.phase is Phase.CANCELLING
            outcome = self.scheduler.worker_lost(w.name, what,
                                                 counts=lost.cause in ("died", "hung"),
                                                 requeue=not self.state.stopping)
            self.state.wake.notify_all()
        log.warning("%s lost (%s): %s", w.name, lost.cause, what)
        if running is not None and outcome.job:
            if lost.cause == "memory":
                self.fail(running, f"the renderer process {what}; this job needs more memory "
                          "than a worker may use: fewer pixels or samples per pixel, or a "
                          "larger limit (matoptd --worker-memory)")
            elif lost.cause == "stopped" and cancelling:
                self.cut_off(running)
            elif outcome.failed:
                self.fail(running, "the renderer process " + ", then ".join(outcome.crashes)
                          + "; a job that takes its worker down twice is not tried again "
                          "(other jobs were not affected)")
            elif lost.cause == "gone":
                self.note_reload(running.name, f"its worker {what}; the job goes on from its "
                                 "last checkpoint on another worker")
            else:
                self.note_reload(running.name, f"the renderer process {what}; the job goes "
                                 "on from its last checkpoint on a fresh worker")
        for name in outcome.others:
            self.note_reload(name, f"its renderer process {lost.reason}; the job goes on "
                             "from its last checkpoint")

    def cut_off(self, record: JobRecord) -> None:
        """A cancel stopped the job's worker mid-iteration: the job is CANCELLED and keeps
        the iterations it finished, its best and last as their records reported them."""
        kept = results_from_history(record, self.store.history(record.name))
        for result in kept:
            self.store.put_result(result)
        large = sorted(k for k in record.shapes
                       if kept and k not in kept[-1].values)
        with self.state.lock:
            self.scheduler.cut_off(record.name)
            if kept:
                shown = ", ".join(f"{r.which.upper()} iteration {r.iteration}" for r in kept)
                record.notes.append(
                    "cancelled during a long iteration: its renderer process was stopped; "
                    f"the results are the finished iterations' values ({shown}), without "
                    "renders or an optimized scene"
                    + (f"; not kept: {', '.join(large)} (too large for the iteration "
                       "records)" if large else ""))
                best = next((r for r in kept if r.which == "best"), None)
                if best is not None:
                    record.best_values = dict(best.values)
            else:
                record.notes.append("cancelled during a long iteration, its first: its "
                                    "renderer process was stopped, so the job has no results")
            self.state.save(record)

    def fail(self, record: JobRecord, message: str) -> None:
        with self.state.lock:
            self.scheduler.fail(record, message)
            self.state.save(record)
            self.state.wake.notify_all()

    def note_reload(self, name: str, note: str) -> None:
        with self.state.lock:
            try:
                record = self.state.record(name)
            except NotFound:
                return
            record.notes.append(note)
            record.resumed_from = RESUME_PENDING
            self.state.save(record)

    def restart(self, w: Handle) -> bool:
        """A fresh process for the lane; False when the daemon stops first or the worker's
        node has left."""
        for delay in RESTART_DELAYS_S + (RESTART_DELAYS_S[-1],) * 1000:
            if self.state.stopped.wait(delay) or w.gone:  # a shutdown cuts the wait short
                return False
            w.state = "restarting"
            w.restarts += 1
            try:
                w.start()
            except WorkerLost as lost:
                log.error("%s did not restart: %s", w.name, lost.reason)
                if w.gone:
                    self.remove(w)
                    return False
                continue
            with self.state.lock:
                self.scheduler.worker_ready(w.name)
                self.state.wake.notify_all()
            return True
        return False

    def remove(self, w: Handle) -> None:
        """A worker whose node left: out of the scheduler and the listing. When it was the
        last, waiting jobs say why they wait."""
        with self.state.lock:
            if w.name not in self.state.workers:
                return
            outcome = self.scheduler.worker_lost(w.name, counts=False,
                                                 requeue=not self.state.stopping)
            self.scheduler.remove_worker(w.name)
            self.state.workers = {n: x for n, x in self.state.workers.items() if n != w.name}
            self.state.wake.notify_all()
        log.warning("%s removed: %s", w.name, w.last_exit)
        for name in [outcome.job] * bool(outcome.job) + outcome.others:
            self.note_reload(name, f"its worker {w.last_exit}; the job goes on from its "
                             "last checkpoint on another worker")
        self.note_waiting()

    def note_waiting(self) -> None:
        """With no worker left, jobs wait QUEUED (they do not fail) and say why."""
        with self.state.lock:
            if any(not w.gone and w.state != "failed" for w in self.state.workers.values()):
                return
            for job in self.scheduler.jobs.values():
                if job.wants_worker and WAITING not in job.record.notes:
                    job.record.notes.append(WAITING)
                    self.state.save(job.record)

    # -- a full disk ------------------------------------------------------------------------

    def hold(self, w: Handle, action: Action) -> None:
        """The disk is full: what the action produced cannot be recorded. Its job's run is
        released, to be loaded again from its last checkpoint (its history is cut back to it
        then), and nothing starts until space returns (the monitor checks)."""
        log.error("the data directory's disk is full: jobs are held until space is freed")
        if action.kind != "task":
            try:
                EngineClient(w, self.watchdog).release(action.job)
            except (UserError, WorkerLost):
                pass
        with self.state.lock:
            self.scheduler.held = True
            if action.kind == "task":
                self.scheduler.done(action)
            else:
                self.scheduler.drop_run(action)

    def unhold(self) -> None:
        """Space is back: what could not be recorded is (pauses carried out meanwhile), and
        the lanes go on."""
        with self.state.lock:
            for job in list(self.scheduler.jobs.values()):
                self.state.save(job.record)
            self.scheduler.held = False
            self.state.wake.notify_all()
