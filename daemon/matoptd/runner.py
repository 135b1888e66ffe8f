"""Carrying out the scheduler's decisions: one lane (a thread) per worker process.

A lane starts its worker, then loops: ask the scheduler what the worker does next, do it
through the engine interface (``engine_api``, called in the worker process), record what came
of it in the store and tell the job's watchers. When the worker is lost (it died, exceeded its
memory limit, or stopped answering), the lane settles what that costs (the job that was
running is retried once from its checkpoint; a second loss fails it with a message saying
what happened), starts a fresh process and goes on. Other workers and the API never wait.

Handlers reach jobs through the methods of ``Runner``: they change state (in the scheduler and
the store) and return; the only thing a handler waits on a worker for is a scene task it
asked for (``task``). Status calls (GetJob, ListJobs, WatchJob) never reach a worker.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from google.protobuf.timestamp_pb2 import Timestamp

from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb

from . import convert, engine_api as api
from .errors import DiskFull, FailedPrecondition, Internal, InvalidArgument, NotFound, \
    ResourceExhausted, Unavailable, UserError
from .events import EventQueue
from .scheduler import Action, Scheduler
from .store import Store
from .workers import CallFailed, Worker, WorkerLost

log = logging.getLogger("matoptd.runner")

FINAL = (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED, pb.JOB_STATE_CANCELLED)
CHECKPOINT_ITERATIONS = 10  # a lost worker costs a job at most this many iterations...
CHECKPOINT_SECONDS = 2.0    # ...or this much time, whichever is more
CANCEL_GRACE_S = 3.0        # a cancel inside a long iteration stops the worker after this
SHUTDOWN_GRACE_S = 10.0     # on shutdown, an iteration running longer is cut off
RESTART_DELAYS_S = (0.0, 1.0, 5.0, 30.0)  # between failed restarts of a worker
WATCH_QUEUE = 10000
MONITOR_PERIOD_S = 0.1


def now() -> Timestamp:
    ts = Timestamp()
    ts.GetCurrentTime()
    return ts


def stop_note(reason: str, job: pb.Job) -> str:
    """Why a job ended, in words: a job that stops early must say so, since "SUCCEEDED" alone
    reads as converged."""
    if reason == "min_error":
        return (f"stopped at iteration {job.iteration} of {job.spec.iterations}: the loss "
                f"{job.best_loss:.4g} fell below min_error {job.spec.min_error:g}")
    if reason == "iterations":
        return f"stopped after all {job.spec.iterations} iterations"
    return f"stopped at iteration {job.iteration} of {job.spec.iterations}: {reason}"

class RemoteEngine:
    """The engine interface of one worker for one action: ``engine.render(...)`` is a call in
    the worker process, under the watchdog's deadline, its failures in the daemon's terms."""

    def __init__(self, worker: Worker, timeout: float) -> None:
        self._worker, self._timeout = worker, timeout

    def __getattr__(self, method: str) -> Callable[..., Any]:
        def call(*args: Any) -> Any:
            try:
                return self._worker.call(method, *args, timeout=self._timeout)
            except CallFailed as exc:
                raise user_error(exc) from None
        return call


def user_error(exc: CallFailed) -> Exception:
    if exc.kind == "invalid":
        return InvalidArgument(str(exc))
    if exc.kind == "memory":
        return ResourceExhausted(f"out of memory: {exc}")
    if exc.kind == "engine":
        return FailedPrecondition(str(exc))
    return Internal(f"the renderer failed: {exc}")


@dataclass
class _Watchers:
    queues: list[tuple[asyncio.AbstractEventLoop, EventQueue]] = field(default_factory=list)


class Runner:
    def __init__(self, store: Store, workers: list[Worker], watchdog: float,
                 slice_seconds: float | None = None, max_samples: int = 0) -> None:
        self.store = store
        self.max_samples = max_samples  # of one render call; results keep to it too
        self.workers = {w.name: w for w in workers}
        self.watchdog = watchdog
        self.scheduler = Scheduler(**({"slice_seconds": slice_seconds}
                                      if slice_seconds is not None else {}))
        for w in workers:
            self.scheduler.add_worker(w.name)
        self.lock = threading.RLock()
        self.wake = threading.Condition(self.lock)
        self.stopping = False
        self._stopped = threading.Event()
        self._lanes: list[threading.Thread] = []
        self._first_start: dict[str, concurrent.futures.Future] = {}
        self._watchers: dict[str, _Watchers] = collections.defaultdict(_Watchers)
        self._shapes: dict[str, dict[str, list[int]]] = {}
        self._checkpointed: dict[str, tuple[int, float]] = {}  # iteration, time
        self._cancelled_at: dict[str, float] = {}
        # Jobs in their end phase: the state and reason they end with, and the result images
        # made so far (per result, "best"/"last"), one sensor per "results" action.
        self._ending: dict[str, tuple[int, str]] = {}
        self._images: dict[str, dict[str, list[pb.Image]]] = {}
        self._monitor = threading.Thread(target=self._watch_workers, name="matoptd-monitor",
                                         daemon=True)
        self._recover()

    # -- life cycle -------------------------------------------------------------------------

    def start(self) -> list[str]:
        """Starts every worker (in its lane) and waits for each to be ready or to fail;
        returns why the ones that failed did. The lanes of failed workers end."""
        for w in self.workers.values():
            self._first_start[w.name] = concurrent.futures.Future()
            self._start_lane(w)
        failures = [f.result() for f in self._first_start.values()]
        self._monitor.start()
        return [f for f in failures if f]

    def add_worker(self, w: Worker) -> None:
        """A worker that joined while the daemon runs (a Ray node came up): its lane starts
        it and it takes work once ready."""
        with self.lock:
            if self.stopping:
                return
            # A new dict rather than a change to it: other threads iterate the old one.
            self.workers = {**self.workers, w.name: w}
            self.scheduler.add_worker(w.name)
        self._start_lane(w)

    def retire(self, name: str, why: str) -> None:
        """The worker's node left: it is not restarted, and its lane ends once whatever it
        was doing has been settled (a call in flight fails when its process goes)."""
        w = self.workers.get(name)
        if w is not None and not w.gone:
            w.gone, w.last_exit = True, why
            with self.lock:
                self.wake.notify_all()

    def _start_lane(self, w: Worker) -> None:
        lane = threading.Thread(target=self._lane, args=(w,), name=f"lane-{w.name}",
                                daemon=True)
        self._lanes.append(lane)
        lane.start()

    @property
    def ready(self) -> bool:
        return any(w.state in ("idle", "busy") for w in self.workers.values())

    @property
    def serving(self) -> bool:
        """Whether the service can do work: a worker runs and results can be recorded."""
        return self.ready and not self.scheduler.held and self.store.full_since is None

    def stop(self) -> None:
        """Finishes the iterations in flight (cutting off any that runs past a grace period),
        checkpoints loaded jobs, marks running ones INTERRUPTED and stops the workers."""
        with self.lock:
            self.stopping = True
            self._stopped.set()
            self.wake.notify_all()
        deadline = time.monotonic() + SHUTDOWN_GRACE_S
        for lane in self._lanes:
            lane.join(max(0.0, deadline - time.monotonic()))
        for w in self.workers.values():
            if w.state == "busy":
                w.kill("was stopped: the daemon shut down during a long iteration", "stopped")
        for lane in self._lanes:
            lane.join()
        with self.lock:
            for job in self.store.list_jobs(None, 0, 1 << 30, (pb.JOB_STATE_RUNNING,)):
                self._interrupt(job, "the daemon was shut down")

    def _recover(self) -> None:
        """After a restart: jobs that were running when the daemon stopped are INTERRUPTED
        (ResumeJob continues them); queued ones run again."""
        for job in self.store.list_jobs(None, 0, 1 << 30, (pb.JOB_STATE_RUNNING, pb.JOB_STATE_QUEUED)):
            if job.state == pb.JOB_STATE_RUNNING:
                self._interrupt(job, "the daemon stopped while the job ran")
            else:
                self.scheduler.add_job(job.name, job.owner,
                                       started=self.store.has_checkpoint(job.name))

    def _interrupt(self, job: pb.Job, why: str) -> None:
        cp = self._checkpointed.get(job.name)
        _phase(job, "")
        job.state = pb.JOB_STATE_INTERRUPTED
        job.stop_reason = (f"{why}; resume continues from the checkpoint at iteration {cp[0]}"
                           if cp else why)
        self._save(job)

    # -- what handlers call -----------------------------------------------------------------

    def submit(self, job: pb.Job) -> None:
        with self.lock:
            self.scheduler.add_job(job.name, job.owner)
            self.wake.notify_all()
        self._note_waiting()

    async def task(self, fn: Callable[[RemoteEngine], Any]) -> Any:
        """Runs ``fn(engine)`` on the next free worker, before any job's next iteration."""
        fut: concurrent.futures.Future = concurrent.futures.Future()
        with self.lock:
            if self.stopping:
                raise Unavailable("the daemon is shutting down")
            if self.scheduler.held:
                raise DiskFull()
            if not any(w.state != "failed" for w in self.workers.values()):
                raise Unavailable("no renderer worker is running (matopt info lists them); "
                                  "try again once one is: jobs already created wait for it")
            self.scheduler.add_task((fn, fut))
            self.wake.notify_all()
        return await asyncio.wrap_future(fut)

    def pause(self, owner: str, name: str) -> pb.Job:
        log.info("%s: pause requested by %s", name, owner)
        with self.lock:
            job = self.store.get_job(name, owner)
            if job.state in (pb.JOB_STATE_QUEUED, pb.JOB_STATE_RUNNING):
                if self.scheduler.pause(name):
                    job.state = pb.JOB_STATE_PAUSED
                    self._save(job)
                self.wake.notify_all()
            elif job.state != pb.JOB_STATE_PAUSED:
                raise FailedPrecondition(f"job '{name}' is {enums.short_name(pb.JobState, job.state)}: only a "
                                         "queued or running job can be paused")
            return job

    def resume(self, owner: str, name: str) -> pb.Job:
        log.info("%s: resume requested by %s", name, owner)
        with self.lock:
            job = self.store.get_job(name, owner)
            if job.state in (pb.JOB_STATE_QUEUED, pb.JOB_STATE_RUNNING):
                self.scheduler.resume(name)  # a pending pause is withdrawn
                return job
            if job.state not in (pb.JOB_STATE_PAUSED, pb.JOB_STATE_INTERRUPTED):
                raise FailedPrecondition(f"job '{name}' is {enums.short_name(pb.JobState, job.state)}: only a "
                                         "paused or interrupted job can be resumed")
            if name in self.scheduler.jobs:
                self.scheduler.resume(name)
            else:
                self.scheduler.add_job(name, job.owner, started=self.store.has_checkpoint(name))
            job.state, job.resumed_from = pb.JOB_STATE_QUEUED, "pending"  # the load says from where
            self._save(job)
            self.wake.notify_all()
            return job

    def cancel(self, owner: str, name: str) -> pb.Job:
        log.info("%s: cancel requested by %s", name, owner)
        with self.lock:
            job = self.store.get_job(name, owner)
            if job.state in FINAL:
                raise FailedPrecondition(f"job '{name}' already ended "
                                         f"({enums.short_name(pb.JobState, job.state)})")
            if name not in self.scheduler.jobs:  # paused or interrupted, not loaded
                self.scheduler.add_job(name, job.owner, paused=True,
                                       started=self.store.has_checkpoint(name))
            if self.scheduler.cancel(name):
                job.state, job.stop_reason = pb.JOB_STATE_CANCELLED, "cancelled"
                self._save(job)
            elif not self.scheduler.jobs[name].ending:
                self._cancelled_at[name] = time.monotonic()
                _phase(job, "cancel requested: the job stops at its next iteration boundary, "
                       "then renders its result images one sensor at a time (other jobs run "
                       "in between) and ends CANCELLED")
                self._save(job)
                self.wake.notify_all()
            return job

    def delete(self, owner: str, name: str) -> None:
        with self.lock:
            job = self.store.get_job(name, owner)
            sched = self.scheduler.jobs.get(name)
            if job.state == pb.JOB_STATE_RUNNING or (sched and (sched.busy or sched.worker)):
                raise FailedPrecondition(f"job '{name}' is {enums.short_name(pb.JobState, job.state)}: cancel "
                                         "it before deleting it")
            self.scheduler.remove(name)
            self.store.delete_job(name)

    def worker_listing(self, user: str) -> list[pb.Worker]:
        """The workers as GetServerInfo shows them: the caller's own jobs by name."""
        states = {"starting": pb.WORKER_STATE_STARTING, "idle": pb.WORKER_STATE_IDLE,
                  "busy": pb.WORKER_STATE_BUSY, "restarting": pb.WORKER_STATE_RESTARTING,
                  "failed": pb.WORKER_STATE_FAILED}
        out = []
        with self.lock:
            for w in self.workers.values():
                loaded = list(self.scheduler.workers[w.name].resident)
                mine = [j for j in loaded if self.scheduler.jobs[j].user == user]
                out.append(pb.Worker(
                    name=w.name, state=states[w.state], variant=w.info.get("variant", ""),
                    device=w.info.get("device", w.placement.describe()),
                    host=w.info.get("host", ""), pid=w.pid, jobs=mine, job_count=len(loaded),
                    restarts=w.restarts, last_exit=w.last_exit, memory_bytes=w.memory(),
                    memory_limit_bytes=w.memory_limit,
                    threads=w.info.get("threads", w.placement.threads), node=w.node))
        return out

    # -- watching ---------------------------------------------------------------------------

    def subscribe(self, name: str) -> EventQueue:
        q = EventQueue(maxsize=WATCH_QUEUE)
        with self.lock:
            self._watchers[name].queues.append((asyncio.get_running_loop(), q))
        return q

    def unsubscribe(self, name: str, q: EventQueue) -> None:
        with self.lock:
            w = self._watchers.get(name)
            if w:
                w.queues = [(lp, x) for lp, x in w.queues if x is not q]
                if not w.queues:
                    del self._watchers[name]

    def _publish(self, name: str, events: list[pb.JobEvent]) -> None:
        """Hands events to every watcher: one wake-up per event loop, not per watcher."""
        by_loop: dict[asyncio.AbstractEventLoop, list[EventQueue]] = {}
        with self.lock:
            for loop, q in self._watchers.get(name, _Watchers()).queues:
                by_loop.setdefault(loop, []).append(q)
        for loop, queues in by_loop.items():
            try:
                loop.call_soon_threadsafe(_offer, queues, events)
            except RuntimeError:  # that loop is closed: its watchers are gone
                pass

    def _save(self, job: pb.Job) -> None:
        job.update_time.CopyFrom(now())
        self.store.put_job(job)
        self._publish(job.name, [pb.JobEvent(job=job)])

    # -- lanes ------------------------------------------------------------------------------

    def _lane(self, w: Worker) -> None:
        first = self._first_start.get(w.name) or concurrent.futures.Future()
        try:
            w.start()
        except WorkerLost as lost:
            w.state = "failed"
            first.set_result(f"{w.name} ({w.placement.describe()}): {lost.reason}")
            if w.gone:
                self._remove(w)
            return
        first.set_result("")
        with self.lock:
            self.scheduler.worker_ready(w.name)
            self.wake.notify_all()
        while True:
            action = self._next(w)
            if action is None:
                break
            try:
                self._do(w, action)
            except WorkerLost as lost:
                self._settle(w, action, lost)
                if w.gone:
                    self._remove(w)
                if self.stopping or not self._restart(w):
                    return
            except DiskFull:
                self._hold(w, action)
            except Exception:  # noqa: BLE001 - a lane must outlive any one job's failure
                log.exception("%s: %s of %s failed", w.name, action.kind, action.job)
                self._give_up(w, action)
        self._close(w)
        if w.gone:
            self._remove(w)

    def _next(self, w: Worker) -> Action | None:
        with self.lock:
            while not self.stopping and not w.gone:
                action = self.scheduler.next(w.name)
                if action is not None:
                    return action
                self.wake.wait(1.0)
        return None

    def _done(self, action: Action, iterations: int = 0, finished: bool = False) -> None:
        with self.lock:
            self.scheduler.done(action, iterations, finished)
            self.wake.notify_all()

    def _timeout(self, action: Action) -> float:
        """The watchdog: a call is hung when it runs far past what its job's pace predicts.
        A load or a first iteration (kernels to compile), a scene task or the results have no
        pace yet and get five times the base."""
        job = self.scheduler.jobs.get(action.job)
        if action.kind == "step" and job is not None and job.per_iteration:
            return max(self.watchdog, 20 * action.n * job.per_iteration)
        if action.kind in ("evict", "park") and job is not None and job.per_iteration:
            return max(self.watchdog, 20 * job.per_iteration)
        return 5 * self.watchdog

    def _do(self, w: Worker, action: Action) -> None:
        engine = RemoteEngine(w, self._timeout(action))
        if action.kind == "task":
            fn, fut = action.task
            try:
                if fut.set_running_or_notify_cancel():
                    try:
                        fut.set_result(fn(engine))
                    except WorkerLost as lost:
                        fut.set_exception(Internal(
                            f"the renderer process {lost.reason} while serving this request; "
                            "the daemon and other users' jobs are unaffected"))
                        raise
                    except BaseException as exc:  # noqa: BLE001 - handed to the caller
                        fut.set_exception(exc)
            finally:
                if w.state != "restarting":
                    self._done(action)
            return
        try:
            job = self.store.get_job(action.job)
        except NotFound:  # deleted meanwhile
            with self.lock:
                self.scheduler.remove(action.job)
            self._done(action, finished=True)
            return
        try:
            if action.kind == "load":
                self._load(engine, job, action)
            elif action.kind == "step":
                self._step(engine, job, action)
            elif action.kind in ("evict", "park"):
                self._unload(engine, job, action)
            elif action.kind == "cancel":
                self._end(job, action, pb.JOB_STATE_CANCELLED, "cancelled")
            elif action.kind == "results":
                self._results(engine, job, action)
            elif action.kind == "finish":
                state, reason = self._ending.get(job.name, (pb.JOB_STATE_CANCELLED, "cancelled"))
                self._finish(engine, job, action, state, reason,
                             cancelled=state == pb.JOB_STATE_CANCELLED)
        except UserError as exc:
            self._fail(engine, job, action, str(exc))

    def _load(self, engine: RemoteEngine, job: pb.Job, action: Action) -> None:
        scene = self.store.get_scene(job.owner, job.spec.scene)
        settings = convert.job_settings(job.spec, self.scene_input(scene),
                                        self.store.read_blob, self.max_samples)
        started: api.Started = engine.start(job.name, settings,
                                            self.store.read_checkpoint(job.name))
        self._shapes[job.name] = started.shapes
        # The first checkpoint after a load is due after CHECKPOINT_ITERATIONS, however fast.
        self._checkpointed[job.name] = (started.iteration, -math.inf)
        with self.lock:
            job = self.store.get_job(job.name)
            if job.state == pb.JOB_STATE_QUEUED:
                job.state = pb.JOB_STATE_RUNNING
            job.integrator, job.integrator_reason = started.integrator, started.integrator_reason
            job.worker = action.worker
            job.sensors_rendered[:] = started.sensors
            job.notes.extend(n for n in started.notes if n not in job.notes)
            if job.resumed_from == "pending":
                job.resumed_from = (f"checkpoint at iteration {started.iteration}"
                                    if started.iteration else "from the start")
            self.store.truncate_history(job.name, started.iteration)  # they will run again
            self._save(job)
        self._done(action)

    def _step(self, engine: RemoteEngine, job: pb.Job, action: Action) -> None:
        progress: api.Progress = engine.step(job.name, action.n)
        shapes = self._shapes.get(job.name, {})
        names = convert.reference_names(job.spec)
        records = [convert.record_to_pb(r, shapes, names) for r in progress.records]
        for record in records:
            self.store.add_iteration(job.name, record)
        with self.lock:
            job = self.store.get_job(job.name)
            convert.progress_to_job(job, progress)
            self.store.put_job(job)
        # The job after its iterations: clients show its best_iteration/best_loss rather than
        # compute their own (for dual_buffer the best is a windowed mean, not a record's loss).
        self._publish(job.name, [pb.JobEvent(iteration=r) for r in records]
                      + [pb.JobEvent(job=job)])
        if progress.done:
            self._end(job, action, pb.JOB_STATE_SUCCEEDED, progress.stop_reason, len(records))
            return
        at, when = self._checkpointed.get(job.name, (0, 0.0))
        if (job.iteration - at >= CHECKPOINT_ITERATIONS
                and time.monotonic() - when >= CHECKPOINT_SECONDS):
            self.store.write_checkpoint(job.name, engine.checkpoint(job.name))
            self._checkpointed[job.name] = (job.iteration, time.monotonic())
        self._done(action, iterations=len(records))

    def _end(self, job: pb.Job, action: Action, state: int, reason: str,
             iterations: int = 0) -> None:
        """The iterations are over: the end phase begins, one "results" action per rendered
        sensor (scheduled like iterations, so other jobs go on between them), then "finish"."""
        with self.lock:
            self._cancelled_at.pop(job.name, None)  # result renders are not cut off
            self._ending[job.name] = (state, reason)
            job = self.store.get_job(job.name)
            parts = len(job.sensors_rendered) if job.iteration else 0
            ended = (f"cancelled at iteration {job.iteration}" if state == pb.JOB_STATE_CANCELLED
                     else f"iterations over ({reason})")
            _phase(job, f"{ended}: rendering result images 0/{parts}" if parts else ended)
            self._save(job)
            self.scheduler.done(action, iterations)
            self.scheduler.end(job.name, parts)
            self.wake.notify_all()

    def _results(self, engine: RemoteEngine, job: pb.Job, action: Action) -> None:
        """One sensor's result images, stored at once; the job's notes count them."""
        sensor = job.sensors_rendered[action.n]
        made: dict[str, list[api.Image]] = engine.result_images(job.name, sensor)
        put = self.store.writer(job.owner)
        stored = {which: [convert.image_to_pb(i, put) for i in images]
                  for which, images in made.items()}
        with self.lock:
            kept = self._images.setdefault(job.name, {})
            for which, images in stored.items():
                kept.setdefault(which, []).extend(images)
            job = self.store.get_job(job.name)
            total = len(job.sensors_rendered)
            phase = next((n for n in job.notes if n.startswith(PHASE)), PHASE)
            _phase(job, phase.removeprefix(PHASE).rsplit(" ", 1)[0]
                   + f" {action.n + 1}/{total}")
            self._save(job)
            self.scheduler.done(action)
            self.wake.notify_all()

    def _unload(self, engine: RemoteEngine, job: pb.Job, action: Action) -> None:
        """Evict (the job waits for its next slice) or park (it is paused): either way the
        worker's memory goes back and the job continues later, anywhere, bit for bit."""
        self.store.write_checkpoint(job.name, engine.checkpoint(job.name))
        self._checkpointed[job.name] = (job.iteration, time.monotonic())
        engine.release(job.name)
        with self.lock:
            if action.kind == "park":
                job = self.store.get_job(job.name)
                job.state = pb.JOB_STATE_PAUSED
                self._save(job)
            self.scheduler.done(action)
            self.wake.notify_all()

    def _finish(self, engine: RemoteEngine, job: pb.Job, action: Action, state: int, reason: str,
                cancelled: bool = False, iterations: int = 0) -> None:
        history = [convert.record_from_pb(r) for r in self.store.history(job.name)]
        finished: api.Finished = engine.finish(job.name, history, cancelled, False)
        scene = self.store.get_scene(job.owner, job.spec.scene)
        shapes = self._shapes.get(job.name, {})
        made = self._images.get(job.name, {})
        best: list[pb.ParameterValue] = []
        for result in finished.results:
            out = convert.result_to_pb(job.name, result, shapes, scene,
                                       self.store.writer(job.owner),
                                       convert.reference_names(job.spec))
            if result.which == "best":  # shown by GetJob, with the standard errors
                best = [p for p in out.parameters if not p.blob]
            images = made.get(result.which, []) + list(out.images)  # sensors, then textures
            del out.images[:]
            out.images.extend(images)
            self.store.put_result(out)
        engine.release(job.name)
        with self.lock:
            job = self.store.get_job(job.name)
            _phase(job, "")
            if cancelled:
                job.notes.append(f"cancelled at iteration {job.iteration}; the results show "
                                 "the best and the last iteration run")
            job.notes.extend(finished.notes)
            job.best_parameters.extend(best)
            if not cancelled:
                job.notes.append(stop_note(reason, job))
            convert.counters_to_job(job, finished.counters)
            job.state, job.stop_reason = state, reason
            self._save(job)
            log.info("%s %s at iteration %d (%s)", job.name, enums.short_name(pb.JobState, state),
                     job.iteration, reason)
            self._forget(job.name)
            self.scheduler.done(action, iterations, finished=True)
            self.wake.notify_all()

    def _fail(self, engine: RemoteEngine | None, job: pb.Job, action: Action,
              message: str) -> None:
        if engine is not None and action.kind in ("step", "evict", "park", "cancel", "results",
                                                  "finish"):
            try:
                engine.release(job.name)
            except UserError:
                pass
        with self.lock:
            try:
                job = self.store.get_job(job.name)
            except NotFound:  # deleted meanwhile
                pass
            else:
                job.state, job.error, job.stop_reason = pb.JOB_STATE_FAILED, message, "failed"
                self._save(job)
            self._forget(job.name)
            self.scheduler.remove(job.name)
            self.scheduler.done(action, finished=True)
            self.wake.notify_all()

    def _hold(self, w: Worker, action: Action) -> None:
        """The disk is full: what the action produced cannot be recorded. Its job's run is
        released, to be loaded again from its last checkpoint (its history is cut back to it
        then), and nothing starts until space returns (``_watch_workers`` checks)."""
        log.error("the data directory's disk is full: jobs are held until space is freed")
        if action.kind == "task":
            with self.lock:
                self.scheduler.held = True
                self.scheduler.done(action)
            return
        try:
            w.call("release", action.job, timeout=self.watchdog)
        except (CallFailed, WorkerLost):
            pass
        with self.lock:
            self.scheduler.held = True
            self.scheduler.drop_run(action)
            self._checkpointed.pop(action.job, None)

    def _unhold(self) -> None:
        """Space is back: pauses that could not be recorded are, and the lanes go on."""
        with self.lock:
            for job in list(self.scheduler.jobs.values()):
                if job.control == "pause" and job.worker is None and not job.busy:
                    self.scheduler.pause(job.name)
                    stored = self.store.get_job(job.name)
                    stored.state = pb.JOB_STATE_PAUSED
                    self._save(stored)
            self.scheduler.held = False
            self.wake.notify_all()

    def _give_up(self, w: Worker, action: Action) -> None:
        """An unexpected failure (a bug): the job fails with what is known, the lane goes on."""
        try:
            job = self.store.get_job(action.job) if action.job else None
            if job is not None:
                self._fail(RemoteEngine(w, self.watchdog), job, action,
                           "internal error in the daemon; the job was stopped (see its log)")
                return
        except DiskFull:
            self._hold(w, action)
            return
        except Exception:  # noqa: BLE001 - already logged once
            log.exception("%s: could not record the failure", w.name)
        with self.lock:
            if action.job:
                self.scheduler.remove(action.job)
            self.scheduler.done(action, finished=True)
            self.wake.notify_all()

    def _forget(self, name: str) -> None:
        for d in (self._shapes, self._checkpointed, self._cancelled_at, self._ending,
                  self._images):
            d.pop(name, None)

    def _close(self, w: Worker) -> None:
        """The daemon stops: checkpoint what the worker holds, then stop the process."""
        with self.lock:
            loaded = list(self.scheduler.workers[w.name].resident)
        for name in loaded:
            try:
                self.store.write_checkpoint(name, w.call("checkpoint", name,
                                                         timeout=self.watchdog))
                self._checkpointed[name] = (self.store.get_job(name).iteration,
                                            time.monotonic())
            except (CallFailed, WorkerLost, NotFound) as exc:
                log.error("could not checkpoint %s on shutdown: %s", name, exc)
        w.stop()

    # -- losing a worker --------------------------------------------------------------------

    def _settle(self, w: Worker, action: Action, lost: WorkerLost) -> None:
        """What the loss of a worker costs: the job it ran (retried once from its checkpoint,
        or failed with what happened) and the jobs it held (reloaded elsewhere)."""
        try:
            running = self.store.get_job(action.job) if action.job else None
        except NotFound:
            running = None
        what = lost.reason
        if running is not None:
            what += (f" during iteration {running.iteration}" if action.kind == "step" else
                     f" while {_DOING[action.kind]}")
        with self.lock:
            outcome = self.scheduler.worker_lost(w.name, what,
                                                 counts=lost.cause in ("died", "hung"))
            self.wake.notify_all()
        log.warning("%s lost (%s): %s", w.name, lost.cause, what)
        if running is not None and outcome.job:
            if lost.cause == "memory":
                with self.lock:
                    self.scheduler.remove(running.name)
                self._fail(None, running, action, f"the renderer process {what}; this job "
                           "needs more memory than a worker may use: fewer pixels or samples "
                           "per pixel, or a larger limit (matoptd --worker-memory)")
            elif lost.cause == "stopped" and running.name in self._cancelled_at:
                with self.lock:
                    self.scheduler.remove(running.name)
                    job = self.store.get_job(running.name)
                    job.state, job.stop_reason = pb.JOB_STATE_CANCELLED, "cancelled"
                    job.notes.append("cancelled during a long iteration: its renderer process "
                                     "was stopped, so the job has no results")
                    self._save(job)
                    self._forget(running.name)
            elif outcome.failed:
                self._fail(None, running, action, "the renderer process " + ", then ".join(
                    outcome.crashes) + "; a job that takes its worker down twice is not "
                    "tried again (other jobs were not affected)")
            elif lost.cause == "gone":
                self._note_reload(running.name, f"its worker {what}; the job goes on from its "
                                  "last checkpoint on another worker")
            else:
                self._note_reload(running.name, f"the renderer process {what}; the job goes "
                                  "on from its last checkpoint on a fresh worker")
        for name in outcome.others:
            self._note_reload(name, f"its renderer process {lost.reason}; the job goes on "
                              "from its last checkpoint")

    def _note_reload(self, name: str, note: str) -> None:
        with self.lock:
            try:
                job = self.store.get_job(name)
            except NotFound:
                return
            job.notes.append(note)
            job.resumed_from = "pending"
            if job.state == pb.JOB_STATE_RUNNING and not self.stopping:  # it waits for a worker again
                job.state = pb.JOB_STATE_QUEUED  # (on shutdown it stays RUNNING, to be INTERRUPTED)
            self._save(job)

    def _remove(self, w: Worker) -> None:
        """A worker whose node left: out of the scheduler and the listing. When it was the
        last, waiting jobs say why they wait."""
        with self.lock:
            if w.name not in self.workers:
                return
            outcome = self.scheduler.worker_lost(w.name, counts=False)
            self.scheduler.remove_worker(w.name)
            self.workers = {n: x for n, x in self.workers.items() if n != w.name}
            self.wake.notify_all()
        log.warning("%s removed: %s", w.name, w.last_exit)
        for name in [outcome.job] * bool(outcome.job) + outcome.others:
            self._note_reload(name, f"its worker {w.last_exit}; the job goes on from its "
                              "last checkpoint on another worker")
        self._note_waiting()

    def _note_waiting(self) -> None:
        """With no worker left, jobs wait QUEUED (they do not fail) and say why."""
        with self.lock:
            if any(not w.gone and w.state != "failed" for w in self.workers.values()):
                return
            note = ("waiting: no renderer worker is available (every worker's machine has "
                    "left, or none has joined yet); the job runs when one joins")
            for name, sched in self.scheduler.jobs.items():
                if not sched.wants_worker:
                    continue
                job = self.store.get_job(name)
                if note not in job.notes:
                    job.notes.append(note)
                    self._save(job)

    def _restart(self, w: Worker) -> bool:
        """A fresh process for the lane; False when the daemon stops first or the worker's
        node has left."""
        for delay in RESTART_DELAYS_S + (RESTART_DELAYS_S[-1],) * 1000:
            if self._stopped.wait(delay) or w.gone:  # a shutdown cuts the wait short
                return False
            w.state = "restarting"
            w.restarts += 1
            try:
                w.start()
            except WorkerLost as lost:
                log.error("%s did not restart: %s", w.name, lost.reason)
                if w.gone:
                    self._remove(w)
                    return False
                continue
            with self.lock:
                self.scheduler.worker_ready(w.name)
                self.wake.notify_all()
            return True
        return False

    def _watch_workers(self) -> None:
        """Memory limits, and cancels that an iteration in flight would keep waiting."""
        while True:
            with self.lock:
                if self.stopping and not any(t.is_alive() for t in self._lanes):
                    return
                late = []
                for name, at in list(self._cancelled_at.items()):
                    action = self.scheduler.in_flight(name)
                    if action is not None and time.monotonic() - at > CANCEL_GRACE_S:
                        late.append(action.worker)
            for w in self.workers.values():
                if w.state == "busy":
                    w.check_memory()
            if (self.scheduler.held or self.store.full_since is not None) \
                    and self.store.space_back() and self.scheduler.held:
                log.info("space on the data directory's disk again: jobs go on")
                try:
                    self._unhold()
                except DiskFull:
                    pass  # filled up again meanwhile
            for name in late:
                if name in self.workers:
                    self.workers[name].kill("was stopped: its job was cancelled during a "
                                            "long iteration", "stopped")
            time.sleep(MONITOR_PERIOD_S)

    # -- scenes -----------------------------------------------------------------------------

    def scene_input(self, scene: pb.Scene) -> api.SceneInput:
        text = self.store.scene_inputs(scene.name)
        if text is None:
            raise FailedPrecondition(f"scene '{scene.name}' was made by an older matoptd; "
                                     "create it again")
        return convert.scene_input_from_json(text)


_DOING = {"load": "loading the job", "evict": "saving the job's checkpoint",
          "park": "pausing the job", "cancel": "stopping the job",
          "results": "rendering the job's result images", "finish": "making the job's results",
          "task": "a task"}
PHASE = "end phase: "  # the note that says what a job in its end phase is doing


def _phase(job: pb.Job, text: str) -> None:
    """Replaces the job's end-phase note with ``text`` (none when empty)."""
    notes = [n for n in job.notes if not n.startswith(PHASE)] + ([PHASE + text] if text else [])
    del job.notes[:]
    job.notes.extend(notes)


def _offer(queues: list[EventQueue], events: list[pb.JobEvent]) -> None:
    for q in queues:
        for event in events:
            q.offer(event)
