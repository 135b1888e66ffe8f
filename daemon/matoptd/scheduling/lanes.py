"""Carrying out the scheduler's decisions: one lane (a thread) per worker.

A lane starts its worker, then loops: ask the scheduler what the worker does next, do it
through the worker's engine (``workers.client.EngineClient``), record what came of it in the
job's record and the store, and tell the job's watchers. A worker that is lost (it died,
exceeded its memory limit, or stopped answering) is settled by ``recovery`` and started
afresh; other workers and the API never wait on it. The only thing a request waits on a lane
for is a scene task it asked for (``Lanes.run_task``); status calls never reach a worker.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

from .. import engine_api as api
from ..errors import DiskFull, Internal, NotFound, Unavailable, UserError
from ..logs import about
from ..records import JobRecord, Phase, RESUME_PENDING
from ..store.outputs import keep_image, keep_result
from ..workers.client import EngineClient
from ..workers.handle import Handle, WorkerLost
from .monitor import Monitor
from .recovery import Recovery
from .scheduler import Action
from .state import State

log = logging.getLogger("matoptd.lanes")

CHECKPOINT_ITERATIONS = 10  # a lost worker costs a job at most this many iterations...
CHECKPOINT_SECONDS = 2.0    # ...or this much time, whichever is more


def stop_note(reason: str, job: JobRecord) -> str:
    """Why a job ended, in words: a job that stops early must say so, since "SUCCEEDED" alone
    reads as converged."""
    s = job.settings
    if reason == "min_error":
        return (f"stopped at iteration {job.iteration} of {s.iterations}: the loss "
                f"{job.best_loss:.4g} fell below min_error {s.min_error:g}")
    if reason == "iterations":
        return f"stopped after all {s.iterations} iterations"
    return f"stopped at iteration {job.iteration} of {s.iterations}: {reason}"


@dataclass
class Task:
    """A request's call on a worker, ``fn(engine)``; ``worker``: where it ran, once begun."""

    fn: Callable[[EngineClient], Any]
    future: concurrent.futures.Future
    worker: str = ""


class Lane:
    """One worker's lane. ``run`` is its thread; ``turn`` is one decision, carried out.

    Just over 300 lines: one method per action kind (load, step, evict, end, results,
    estimate, finish, task), each a few lines of record-keeping around one engine call;
    split, they would pass the record and the action back and forth."""

    def __init__(self, state: State, worker: Handle, watchdog: float, recovery: Recovery
                 ) -> None:
        self.state, self.worker, self.watchdog, self.recovery = state, worker, watchdog, recovery
        self.scheduler, self.store = state.scheduler, state.store

    # -- the loop ---------------------------------------------------------------------------

    def start_worker(self) -> str:
        """Starts the worker; returns why it failed ("" when it is ready)."""
        w = self.worker
        try:
            w.start()
        except WorkerLost as lost:
            w.state = "failed"
            if w.gone:
                self.recovery.remove(w)
            return f"{w.name} ({w.placement.describe()}): {lost.reason}"
        with self.state.lock:
            self.scheduler.worker_ready(w.name)
            self.state.wake.notify_all()
        return ""

    def run(self, started: concurrent.futures.Future) -> None:
        failure = self.start_worker()
        started.set_result(failure)
        if failure:
            return
        while (action := self._next()) is not None:
            if not self.do(action):
                return
        self.close()
        if self.worker.gone:
            self.recovery.remove(self.worker)

    def turn(self) -> Action | None:
        """What the worker does next, done now (None: nothing to do)."""
        with self.state.lock:
            action = self.scheduler.next(self.worker.name)
        if action is not None:
            self.do(action)
        return action

    def _next(self) -> Action | None:
        with self.state.lock:
            while not self.state.stopping and not self.worker.gone:
                action = self.scheduler.next(self.worker.name)
                if action is not None:
                    return action
                self.state.wake.wait(1.0)
        return None

    def do(self, action: Action) -> bool:
        """Carries out the action, whatever becomes of it; False when the lane ends (its
        worker was lost and cannot be started again)."""
        w = self.worker
        try:
            self._carry_out(action)
        except WorkerLost as lost:
            self.recovery.settle(w, action, lost)
            if w.gone:
                self.recovery.remove(w)
            return not self.state.stopping and self.recovery.restart(w)
        except DiskFull:
            self.recovery.hold(w, action)
        except Exception:  # noqa: BLE001 - a lane must outlive any one job's failure
            job = about(action.job, action.user)
            log.exception("%s: %s of %s failed", w.name, action.kind, action.job, extra=job)
            self._give_up(action)
        return True

    def close(self) -> None:
        """The daemon stops: checkpoint what the worker holds, then stop the process."""
        with self.state.lock:
            loaded = list(self.scheduler.workers[self.worker.name].resident)
        engine = EngineClient(self.worker, self.watchdog)
        for name in loaded:
            try:
                self.store.checkpoints.write(name, engine.checkpoint(name))
                with self.state.lock:
                    record = self.state.record(name)
                    record.checkpoint = record.iteration
            except (UserError, WorkerLost) as exc:
                log.error("could not checkpoint %s on shutdown: %s", name, exc, extra=about(name))
        self.worker.stop()

    def _timeout(self, action: Action) -> float:
        """The watchdog: a call is hung when it runs far past what its job's pace predicts.
        A load or a first iteration (kernels to compile), a scene task or the results have no
        pace yet and get five times the base; a fresh load that runs probes (starts compared)
        that for each probe."""
        job = self.scheduler.jobs.get(action.job)
        if action.kind == "step" and job is not None and job.per_iteration:
            return max(self.watchdog, 20 * action.n * job.per_iteration)
        if action.kind in ("evict", "park") and job is not None and job.per_iteration:
            return max(self.watchdog, 20 * job.per_iteration)
        if action.kind == "load" and job is not None and job.record.checkpoint is None:
            return 5 * self.watchdog * max(1, job.record.settings.starts)
        return 5 * self.watchdog

    def _done(self, action: Action, iterations: int = 0, record: JobRecord | None = None,
              estimated: bool = False) -> None:
        """Tells the scheduler; saves the record it may have changed."""
        with self.state.lock:
            self.scheduler.done(action, iterations, estimated)
            if record is not None:
                self.state.save(record)
            self.state.wake.notify_all()

    # -- actions ----------------------------------------------------------------------------

    def _carry_out(self, action: Action) -> None:
        engine = EngineClient(self.worker, self._timeout(action))
        if action.kind == "task":
            self._task(engine, action)
            return
        with self.state.lock:
            try:
                record = self.state.record(action.job)
            except NotFound:  # deleted meanwhile
                self.scheduler.remove(action.job)
                record = None
        if record is None:
            self._done(action)
            return
        act = {"load": self._load, "step": self._step, "evict": self._evict,
               "park": self._park, "cancel": self._cancel, "results": self._results,
               "estimate": self._estimate, "finish": self._finish}[action.kind]
        try:
            act(engine, record, action)
        except DiskFull:
            raise
        except UserError as exc:
            self._fail(engine, record, action, str(exc))

    def _task(self, engine: EngineClient, action: Action) -> None:
        task: Task = action.task
        task.worker = action.worker
        try:
            if task.future.set_running_or_notify_cancel():
                try:
                    task.future.set_result(task.fn(engine))
                except WorkerLost as lost:
                    task.future.set_exception(Internal(
                        f"the renderer process {lost.reason} while serving this request; the "
                        "daemon and other users' jobs are unaffected"))
                    raise
                except BaseException as exc:  # noqa: BLE001 - handed to the caller
                    task.future.set_exception(exc)
        finally:
            if self.worker.state != "restarting":  # a lost worker's action is settled
                self._done(action)

    def _load(self, engine: EngineClient, record: JobRecord, action: Action) -> None:
        self._server_turn()  # the CreateJob or ResumeJob that led here is answered first
        started = engine.start(record.name, record.settings,
                               self.store.checkpoints.read(record.name))
        with self.state.lock:
            record.integrator, record.integrator_reason = (started.integrator,
                                                           started.integrator_reason)
            record.worker, record.sensors = action.worker, list(started.sensors)
            record.shapes, record.choices = dict(started.shapes), list(started.choices)
            record.notes.extend(n for n in started.notes if n not in record.notes)
            if record.resumed_from == RESUME_PENDING:
                record.resumed_from = (f"checkpoint at iteration {started.iteration}"
                                       if started.iteration and started.probed is None
                                       else "from the start")
            # The first checkpoint after a load is due after CHECKPOINT_ITERATIONS, however
            # fast they are.
            record.checkpoint = started.iteration
            self.scheduler.jobs[record.name].checkpointed = -math.inf
            self.store.truncate_history(record.name, started.iteration)  # they run again
        if started.probed is not None:
            # The best probe's iterations are the job's first: kept at once, with a
            # checkpoint, so that the probes never run again.
            self.store.checkpoints.write(record.name, engine.checkpoint(record.name))
            self._progressed(record, started.probed)
        self._done(action, record=record)

    def _progressed(self, record: JobRecord, progress: api.Progress) -> None:
        """Keeps iterations a worker ran and tells the job's watchers."""
        self.store.add_iterations(record.name, progress.records)
        with self.state.lock:
            last = progress.records[-1]
            record.iteration, record.loss = last.iteration + 1, last.loss
            record.best_iteration = progress.best_iteration
            record.best_loss = progress.best_loss if math.isfinite(progress.best_loss) else 0.0
            record.elapsed, record.counters = progress.seconds, progress.counters
            record.choices = list(progress.choices)
            record.updated = self.state.clock.time()
            self.store.put_job(record)
            snapshot = record.snapshot()
        # The job after its iterations: clients show its best_iteration/best_loss rather than
        # compute their own (for dual_buffer the best is a windowed mean, not a record's loss).
        self.state.events.publish(record.name, [*progress.records, snapshot])

    def _step(self, engine: EngineClient, record: JobRecord, action: Action) -> None:
        first = record.iteration == 0
        progress = engine.step(record.name, action.n)
        self._progressed(record, progress)
        if first:
            self._server_turn()  # the first iteration's event goes out before the next
        with self.state.lock:
            job = self.scheduler.jobs[record.name]
        if progress.done:
            self._end(engine, record, action, Phase.SUCCEEDED, progress.stop_reason,
                      len(progress.records))
            return
        now = self.state.clock.monotonic()
        if (record.iteration - (record.checkpoint or 0) >= CHECKPOINT_ITERATIONS
                and now - job.checkpointed >= CHECKPOINT_SECONDS):
            self.store.checkpoints.write(record.name, engine.checkpoint(record.name))
            record.checkpoint, job.checkpointed = record.iteration, now
        self._done(action, len(progress.records))

    def _server_turn(self) -> None:
        """The CPU left to the server for a moment (``State.server_turn``), the worker
        idle: what a client waits on goes out now rather than when the worker next pauses
        (a job's first event came 60-120 ms after its iteration on 2 cores, 20 ms with it)."""
        if self.state.server_turn:
            time.sleep(self.state.server_turn)

    def _evict(self, engine: EngineClient, record: JobRecord, action: Action) -> None:
        """The job waits for its next slice: the worker's memory goes back, and the job
        continues later, anywhere, bit for bit."""
        self._unload(engine, record)
        with self.state.lock:
            self.store.put_job(record)  # (its watchers are told nothing new)
        self._done(action)

    def _park(self, engine: EngineClient, record: JobRecord, action: Action) -> None:
        """As an eviction, but the job is PAUSED (or, cancelled meanwhile, it is loaded again
        to end)."""
        self._unload(engine, record)
        self._done(action, record=record)

    def _unload(self, engine: EngineClient, record: JobRecord) -> None:
        self.store.checkpoints.write(record.name, engine.checkpoint(record.name))
        with self.state.lock:
            record.checkpoint = record.iteration
            self.scheduler.jobs[record.name].checkpointed = self.state.clock.monotonic()
        engine.release(record.name)

    def _cancel(self, engine: EngineClient, record: JobRecord, action: Action) -> None:
        self._end(engine, record, action, Phase.CANCELLED, "cancelled")

    def _end(self, engine: EngineClient, record: JobRecord, action: Action, outcome: Phase,
             reason: str, iterations: int = 0) -> None:
        """The iterations are over: the end phase begins, one "results" action per rendered
        sensor (scheduled like iterations, so other jobs go on between them), then "finish".
        A checkpoint first: a job whose worker is lost in its end phase is loaded again as its
        iterations left it, so its results are still those of its best and last iterations."""
        if record.iteration:
            self.store.checkpoints.write(record.name, engine.checkpoint(record.name))
        with self.state.lock:
            if record.iteration:
                record.checkpoint = record.iteration
            self.scheduler.done(action, iterations)
            self.scheduler.end(record.name, outcome, reason,
                               len(record.sensors) if record.iteration else 0)
            self.state.save(record)
            self.state.wake.notify_all()

    def _results(self, engine: EngineClient, record: JobRecord, action: Action) -> None:
        """One sensor's result images, kept at once; the job's notes count them."""
        made = engine.result_images(record.name, record.sensors[action.n])
        kept = {which: [keep_image(i, self._put(record)) for i in images]
                for which, images in made.items()}
        with self.state.lock:
            for which, images in kept.items():
                record.ending.images.setdefault(which, []).extend(images)
        self._done(action, record=record)

    def _estimate(self, engine: EngineClient, record: JobRecord, action: Action) -> None:
        """A step's time of the job's standard errors (the engine keeps what it has)."""
        estimated = engine.estimate_part(record.name, self.scheduler.step_seconds)
        self._done(action, record=record, estimated=estimated)

    def _finish(self, engine: EngineClient, record: JobRecord, action: Action) -> None:
        ending, cancelled = record.ending, record.ending.outcome is Phase.CANCELLED
        history = self.store.history(record.name)
        finished = engine.finish(record.name, history, cancelled, False)
        scene = self.store.get_scene(record.owner, record.scene)
        kept = [keep_result(record.name, result, record.shapes, scene,
                            ending.images.get(result.which, []), self._put(record))
                for result in finished.results]
        for result in kept:
            self.store.put_result(result)
        best = next((r for r in kept if r.which == "best"), None)
        engine.release(record.name)
        with self.state.lock:
            if cancelled:
                record.notes.append(f"cancelled at iteration {record.iteration}; the results "
                                    "show the best and the last iteration run")
            record.notes.extend(finished.notes)
            if not cancelled:
                record.notes.append(stop_note(ending.reason, record))
            record.counters = finished.counters
            if best is not None:  # GetJob shows them, with their standard errors
                record.best_values = {k: v for k, v in best.values.items() if not v.sha256}
                record.best_errors = best.standard_errors
            self.scheduler.done(action)  # the job is its outcome now
            self.state.save(record)
            self.state.wake.notify_all()
        log.info("%s %s at iteration %d (%s)", record.name, record.phase.name,
                 record.iteration, ending.reason, extra=about(record.name, record.owner))

    def _put(self, record: JobRecord) -> Callable[[bytes], str]:
        return lambda data: self.store.blobs.put(data, record.owner)

    # -- failures ---------------------------------------------------------------------------

    def _fail(self, engine: EngineClient | None, record: JobRecord, action: Action,
              message: str) -> None:
        if engine is not None and action.kind != "load":
            try:
                engine.release(record.name)
            except UserError:
                pass
        with self.state.lock:
            self.scheduler.fail(record, message)
            self.scheduler.done(action)
            self.state.save(record)
            self.state.wake.notify_all()

    def _give_up(self, action: Action) -> None:
        """An unexpected failure (a bug): the job fails with what is known, the lane goes on."""
        try:
            with self.state.lock:
                record = self.state.record(action.job) if action.job else None
            if record is not None:
                self._fail(EngineClient(self.worker, self.watchdog), record, action,
                           "internal error in the daemon; the job was stopped (see its log)")
                return
        except DiskFull:
            self.recovery.hold(self.worker, action)
            return
        except Exception:  # noqa: BLE001 - already logged once
            log.exception("%s: could not record the failure", self.worker.name)
        with self.state.lock:
            if action.job:
                self.scheduler.remove(action.job)
            self.scheduler.done(action)
            self.state.wake.notify_all()


@dataclass
class WorkerStatus:
    """A worker as GetServerInfo shows it: the caller's own jobs by name, others counted."""

    name: str
    state: str
    variant: str
    device: str
    host: str
    pid: int
    jobs: list[str]
    job_count: int
    restarts: int
    last_exit: str
    memory: int
    memory_limit: int
    threads: int
    node: str = ""
    sizing: str = ""  # how many workers share its device, and why


class Lanes:
    """Every worker's lane, and the workers' life: started at once, added when a Ray node
    joins, retired when it leaves, stopped with the daemon."""

    def __init__(self, state: State, workers: list[Handle], watchdog: float,
                 recovery: Recovery) -> None:
        self.state, self.watchdog, self.recovery = state, watchdog, recovery
        self.state.workers = {w.name: w for w in workers}
        for w in workers:
            state.scheduler.add_worker(w.name)
        self._threads: list[threading.Thread] = []
        self.monitor = Monitor(state, self.recovery,
                               lambda: any(t.is_alive() for t in self._threads))

    def start(self) -> list[str]:
        """Starts every worker (in its lane) and waits for each to be ready or to fail;
        returns why the ones that failed did. The lanes of failed workers end."""
        started = [self._start_lane(w) for w in self.state.workers.values()]
        failures = [f.result() for f in started]
        self.monitor.start()
        return [f for f in failures if f]

    def add_worker(self, w: Handle) -> None:
        """A worker that joined while the daemon runs (a Ray node came up): its lane starts
        it and it takes work once ready."""
        with self.state.lock:
            if self.state.stopping:
                return
            # A new dict rather than a change to it: other threads iterate the old one.
            self.state.workers = {**self.state.workers, w.name: w}
            self.state.scheduler.add_worker(w.name)
        self._start_lane(w)

    def retire(self, name: str, why: str) -> None:
        """The worker's node left: it is not restarted, and its lane ends once whatever it
        was doing has been settled (a call in flight fails when its process goes)."""
        w = self.state.workers.get(name)
        if w is not None and not w.gone:
            w.gone, w.last_exit = True, why
            self.state.notify()

    def _start_lane(self, w: Handle) -> concurrent.futures.Future:
        started: concurrent.futures.Future = concurrent.futures.Future()
        lane = Lane(self.state, w, self.watchdog, self.recovery)
        thread = threading.Thread(target=lane.run, args=(started,), name=f"lane-{w.name}",
                                  daemon=True)
        self._threads.append(thread)
        thread.start()
        return started

    def thread_ids(self) -> set[int]:
        """The lanes' threads (the OS's ids), which start the worker processes, and the
        monitor's, whose kills (a cancel or a shutdown past its grace, a worker over its memory)
        must not wait behind the very render they stop."""
        threads = [*self._threads, self.monitor.thread]
        return {t.native_id for t in threads if t.native_id is not None}

    @property
    def step_seconds(self) -> float:
        """About how long one turn of a worker takes (a step call's iterations)."""
        return self.state.scheduler.step_seconds

    @property
    def ready(self) -> bool:
        return any(w.state in ("idle", "busy") for w in self.state.workers.values())

    @property
    def serving(self) -> bool:
        """Whether the service can do work: a worker runs and results can be recorded."""
        return (self.ready and not self.state.scheduler.held
                and self.state.store.disk.full_since is None)

    def begin_stop(self) -> None:
        """No new work; the iterations in flight have their grace from now. Called from the
        signal's own handler, before the rest of a shutdown's work on a niced server."""
        with self.state.lock:
            if self.state.stop_asked is None:
                self.state.stop_asked = self.state.clock.monotonic()
            self.state.stopped.set()
            self.state.wake.notify_all()

    def stop(self) -> None:
        """Finishes the iterations in flight (cutting off any that runs past a grace period),
        checkpoints loaded jobs, marks running ones INTERRUPTED and stops the workers."""
        self.begin_stop()
        for thread in self._threads:  # the monitor cuts off an iteration past its grace
            thread.join()
        self.recovery.interrupt_all("the daemon was shut down")

    def _submit(self, fn: Callable[[EngineClient], Any], worker: str | None = None) -> Task:
        task = Task(fn, concurrent.futures.Future())
        with self.state.lock:
            if self.state.stopping:
                raise Unavailable("the daemon is shutting down")
            if self.state.scheduler.held:
                raise DiskFull()
            if not any(w.state != "failed" for w in self.state.workers.values()):
                raise Unavailable("no renderer worker is running (matopt info lists them); "
                                  "try again once one is: jobs already created wait for it")
            self.state.scheduler.add_task(task, worker)
            self.state.wake.notify_all()
        return task

    async def run_task(self, fn: Callable[[EngineClient], Any]) -> Any:
        """Runs ``fn(engine)`` on the next free worker, before any job's next iteration."""
        return await asyncio.wrap_future(self._submit(fn).future)

    async def run_in_pieces(self, piece: Callable[[EngineClient], Any],
                            abandon: Callable[[EngineClient], None]) -> Any:
        """``piece`` on the next free worker, then on that worker again until it returns
        something other than None: a task of a minute (a paused job's standard errors) as
        tasks of a step's time, with other jobs' turns between them. What a piece leaves
        on its worker for the next is let go by the last piece, or by ``abandon`` when the
        caller goes or a piece fails."""
        worker = None
        try:
            while True:
                task = self._submit(piece, worker)
                out = await asyncio.wrap_future(task.future)
                worker = task.worker
                if out is not None:
                    return out
        except BaseException:
            if worker is not None:
                with contextlib.suppress(UserError):
                    self._submit(abandon, worker)  # not waited for
            raise

    def listing(self, user: str) -> list[WorkerStatus]:
        out = []
        with self.state.lock:
            for w in self.state.workers.values():
                loaded = list(self.state.scheduler.workers[w.name].resident)
                mine = [j for j in loaded if self.state.scheduler.jobs[j].user == user]
                out.append(WorkerStatus(
                    w.name, w.state, w.info.get("variant", ""),
                    w.info.get("device", w.placement.describe()), w.info.get("host", ""),
                    w.pid, mine, len(loaded), w.restarts, w.last_exit, w.memory(),
                    w.memory_limit, w.info.get("threads", w.placement.threads), w.node,
                    w.placement.sizing))
        return out
