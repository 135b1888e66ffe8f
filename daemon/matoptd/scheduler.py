"""The worker thread that owns Dr.Jit, and the jobs taking turns on it.

Mitsuba 3.9 breaks when AD runs in several threads, so exactly one thread calls the engine.
Between two iterations it first runs queued engine tasks (scene loads, renders, reference
checks: short, and a user is waiting on them), then gives one iteration to the next runnable
job in round-robin order, so a long job never starves another user's. Pause, resume and cancel
are requests the worker honours at the next iteration boundary.

Job state lives in the store; this module is what changes it. A lock serializes those changes
between the gRPC handlers (which only flip flags and states of jobs that are not loaded) and
the worker.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import threading
import time
import traceback
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from google.protobuf.timestamp_pb2 import Timestamp

from matopt_api.v1 import matopt_pb2 as pb

from . import scenes
from .errors import FailedPrecondition, UserError
from .store import Store

log = logging.getLogger("matoptd.scheduler")

FINAL = (pb.SUCCEEDED, pb.FAILED, pb.CANCELLED)
CHECKPOINT_EVERY = 10  # iterations; also on pause and shutdown
SCENE_CACHE = 4        # loaded scenes kept for renders


@dataclass
class Run:
    """A job whose optimization is loaded on the worker."""

    opt: Any  # engine.optimize.Optimization
    shapes: dict[str, list[int]]
    kinds: dict[str, int]
    control: str = ""  # "", "pause" or "cancel"


@dataclass
class _Watchers:
    queues: list[tuple[asyncio.AbstractEventLoop, asyncio.Queue]] = field(default_factory=list)


def now() -> Timestamp:
    ts = Timestamp()
    ts.GetCurrentTime()
    return ts


class Scheduler:
    def __init__(self, store: Store, data_dir: Path, variant: str | None) -> None:
        self.store = store
        self.data_dir = Path(data_dir)
        self.requested_variant = variant
        self.variant = self.device = ""
        self._lock = threading.RLock()
        self._wake = threading.Condition(self._lock)
        self._tasks: collections.deque[tuple[Callable[[], Any], Future]] = collections.deque()
        self._runnable: collections.deque[str] = collections.deque()
        self._runs: dict[str, Run] = {}
        self._watchers: dict[str, _Watchers] = collections.defaultdict(_Watchers)
        self._scene_cache: collections.OrderedDict[str, Any] = collections.OrderedDict()
        self._stopping = False
        self._ready = Future()
        self._thread = threading.Thread(target=self._main, name="matoptd-worker", daemon=True)
        self._recover()

    # -- life cycle -------------------------------------------------------------------------

    def start(self) -> None:
        """Starts the worker and waits until the engine is initialised (or raises why not)."""
        self._thread.start()
        self._ready.result()

    def stop(self) -> None:
        """Finishes the current iteration, checkpoints loaded jobs, marks running ones
        INTERRUPTED."""
        with self._lock:
            self._stopping = True
            self._wake.notify_all()
        if self._thread.is_alive():
            self._thread.join()

    def _recover(self) -> None:
        """After a restart: running jobs were interrupted; queued ones run again."""
        for job in self.store.list_jobs(None, 0, 1 << 30, (pb.RUNNING, pb.QUEUED)):
            if job.state == pb.RUNNING:
                job.state = pb.INTERRUPTED
                job.stop_reason = "the daemon stopped while the job ran"
                job.update_time.CopyFrom(now())
                self.store.put_job(job)
            else:
                self._runnable.append(job.name)

    # -- tasks: engine work for the handlers ------------------------------------------------

    def submit(self, fn: Callable[[], Any]) -> Future:
        """Runs ``fn`` on the worker before the next iteration of any job."""
        fut: Future = Future()
        with self._lock:
            if self._stopping:
                fut.set_exception(FailedPrecondition("the daemon is shutting down"))
                return fut
            self._tasks.append((fn, fut))
            self._wake.notify_all()
        return fut

    async def call(self, fn: Callable[[], Any]) -> Any:
        return await asyncio.wrap_future(self.submit(fn))

    def engine(self):
        """The engine module; to be used inside submitted tasks only."""
        from .engine import service
        return service

    def loaded_scene(self, scene: pb.Scene) -> Any:
        """The scene loaded for renders (worker thread only; a small LRU cache)."""
        if scene.name in self._scene_cache:
            self._scene_cache.move_to_end(scene.name)
            return self._scene_cache[scene.name]
        loaded = self.load_scene(scene)
        self._scene_cache[scene.name] = loaded
        while len(self._scene_cache) > SCENE_CACHE:
            self._scene_cache.popitem(last=False)
        return loaded

    def loadable(self, scene: pb.Scene) -> Path:
        """The prepared copy of the scene's main XML (stable ids, float textures, ...)."""
        return (self.scene_dir(scene.name) / scene.main_file).parent / scenes.LOADABLE_NAME

    def load_scene(self, scene: pb.Scene, keys: list[str] | None = None) -> Any:
        """A fresh Mitsuba scene (worker thread only). Jobs get their own: they change it.
        With the ``keys`` a job optimizes, meshes that do not carry them may be merged."""
        return self.engine().load(self.loadable(scene), dict(scene.overrides),
                                  scene.main_file or scene.display_name, keys)

    def forget_scene(self, name: str) -> None:
        self._scene_cache.pop(name, None)

    def scene_dir(self, name: str) -> Path:
        return self.data_dir / "scenes" / name.removeprefix("scenes/")

    # -- watching ---------------------------------------------------------------------------

    def subscribe(self, name: str) -> asyncio.Queue:
        q: asyncio.Queue = asyncio.Queue(maxsize=10000)
        with self._lock:
            self._watchers[name].queues.append((asyncio.get_running_loop(), q))
        return q

    def unsubscribe(self, name: str, q: asyncio.Queue) -> None:
        with self._lock:
            w = self._watchers.get(name)
            if w:
                w.queues = [(lp, x) for lp, x in w.queues if x is not q]
                if not w.queues:
                    del self._watchers[name]

    def _publish(self, name: str, event: pb.JobEvent) -> None:
        """Hands the event to every watcher: one wake-up per event loop, not per watcher, since
        each wake-up takes the GIL from the worker while it prepares the next render."""
        by_loop: dict[asyncio.AbstractEventLoop, list[asyncio.Queue]] = {}
        with self._lock:
            for loop, q in self._watchers.get(name, _Watchers()).queues:
                by_loop.setdefault(loop, []).append(q)
        for loop, queues in by_loop.items():
            try:
                loop.call_soon_threadsafe(_offer, queues, event)
            except RuntimeError:  # that loop is closed: its watchers are gone
                pass

    def _save(self, job: pb.Job) -> None:
        job.update_time.CopyFrom(now())
        self.store.put_job(job)
        self._publish(job.name, pb.JobEvent(job=job))

    # -- control (from handlers) ------------------------------------------------------------

    def enqueue(self, job: pb.Job) -> None:
        with self._lock:
            self._runnable.append(job.name)
            self._wake.notify_all()

    def pause(self, owner: str, name: str) -> pb.Job:
        with self._lock:
            job = self.store.get_job(name, owner)
            if job.state == pb.QUEUED and name not in self._runs:
                if name in self._runnable:
                    self._runnable.remove(name)
                job.state = pb.PAUSED
                self._save(job)
            elif job.state in (pb.QUEUED, pb.RUNNING):
                self._runs[name].control = "pause"
            elif job.state != pb.PAUSED:
                raise FailedPrecondition(f"job '{name}' is {pb.State.Name(job.state)}: only a "
                                         "queued or running job can be paused")
            return job

    def resume(self, owner: str, name: str) -> pb.Job:
        with self._lock:
            job = self.store.get_job(name, owner)
            if job.state in (pb.QUEUED, pb.RUNNING):
                if name in self._runs:
                    self._runs[name].control = ""  # a pending pause is withdrawn
                return job
            if job.state not in (pb.PAUSED, pb.INTERRUPTED):
                raise FailedPrecondition(f"job '{name}' is {pb.State.Name(job.state)}: only a "
                                         "paused or interrupted job can be resumed")
            job.state = pb.QUEUED
            run = self._runs.get(name)
            job.resumed_from = (f"iteration {run.opt.iteration}, kept in memory" if run
                                else "pending")  # _load says from where
            self._save(job)
            self._runnable.append(name)
            self._wake.notify_all()
            return job

    def cancel(self, owner: str, name: str) -> pb.Job:
        with self._lock:
            job = self.store.get_job(name, owner)
            if job.state in FINAL:
                raise FailedPrecondition(f"job '{name}' already ended "
                                         f"({pb.State.Name(job.state)})")
            if name in self._runs:
                self._runs[name].control = "cancel"
                if name not in self._runnable:  # paused: let the worker wrap it up
                    self._runnable.append(name)
                self._wake.notify_all()
            else:
                if name in self._runnable:
                    self._runnable.remove(name)
                job.state, job.stop_reason = pb.CANCELLED, "cancelled"
                self._save(job)
            return job

    def delete(self, owner: str, name: str) -> None:
        with self._lock:
            job = self.store.get_job(name, owner)
            if job.state == pb.RUNNING or name in self._runs:
                raise FailedPrecondition(f"job '{name}' is {pb.State.Name(job.state)}: cancel "
                                         "it before deleting it")
            if name in self._runnable:
                self._runnable.remove(name)
            self.store.delete_job(name)

    # -- the worker -------------------------------------------------------------------------

    def _main(self) -> None:
        try:
            self.variant, self.device = self.engine().init(self.requested_variant,
                                                           self.data_dir)
        except BaseException as exc:  # noqa: BLE001 - reported to start()
            self._ready.set_exception(exc)
            return
        self._ready.set_result(None)
        log.info("engine ready: %s on %s", self.variant, self.device)
        while True:
            with self._lock:
                while not (self._tasks or self._runnable or self._stopping):
                    self._wake.wait()
                if self._stopping:
                    break
                task = self._tasks.popleft() if self._tasks else None
                name = None
                if task is None:
                    name = self._runnable[0]
                    self._runnable.rotate(-1)
            if task is not None:
                fn, fut = task
                if fut.set_running_or_notify_cancel():
                    try:
                        fut.set_result(fn())
                    except BaseException as exc:  # noqa: BLE001 - handed to the caller
                        fut.set_exception(exc)
            else:
                self._turn(name)
        self._shutdown()
        for _, fut in self._tasks:
            fut.cancel()

    def _shutdown(self) -> None:
        for name, run in list(self._runs.items()):
            try:
                job = self.store.get_job(name)
                self._checkpoint(name, run)
                if job.state in (pb.RUNNING, pb.QUEUED):
                    job.state = pb.INTERRUPTED
                    job.stop_reason = "the daemon was shut down; resume continues from the " \
                                      f"checkpoint at iteration {run.opt.iteration}"
                    self._save(job)
            except Exception:  # noqa: BLE001 - best effort on the way out
                log.exception("could not checkpoint %s on shutdown", name)

    def _turn(self, name: str) -> None:
        """One iteration of one job, with everything that can go wrong contained to it.

        Scenes kept loaded for renders are dropped first: Mitsuba dispatches a virtual call
        (a BSDF's, an emitter's) over every live instance in the process, so each scene held
        makes every job's kernels bigger (bench/live_scenes.py measures it)."""
        self._scene_cache.clear()
        with self._lock:
            try:
                job = self.store.get_job(name)
            except UserError:  # deleted meanwhile
                self._drop(name)
                return
            if name not in self._runs and job.state != pb.QUEUED:
                self._drop(name)  # paused or cancelled after this turn was chosen
                return
        try:
            run = self._runs.get(name) or self._load(job)
            if run is None:
                return
            with self._lock:
                control = run.control
                if job.state == pb.QUEUED and not control:  # resumed while kept in memory
                    job.state = pb.RUNNING
                    self._save(job)
            if control == "pause":
                self._checkpoint(name, run)
                with self._lock:
                    run.control = ""
                    self._runnable.remove(name)
                    job.state = pb.PAUSED
                    self._save(job)
                return
            if control == "cancel":
                self._finish(job, run, pb.CANCELLED, "cancelled")
                return
            self._iterate(job, run)
        except UserError as exc:
            self._fail(job, str(exc))
        except Exception as exc:  # noqa: BLE001 - a job's failure must not stop the daemon
            log.error("job %s failed:\n%s", name, traceback.format_exc())
            self._fail(job, f"internal error: {type(exc).__name__}: {exc}")

    def _load(self, job: pb.Job) -> Run | None:
        """Loads a queued job onto the worker; None when a handler paused or cancelled it
        while its scene loaded (it was not in ``_runs`` yet, so the handler changed it)."""
        scene = self.store.get_scene(job.owner, job.spec.scene)
        refs = {}
        for i, ref in enumerate(job.spec.references):
            index = ref.sensor if ref.HasField("sensor") else i
            refs[index] = (self.store.blob_file(ref.blob), ref.filename or ref.blob)
        blob = self.store.checkpoint(job.name)
        checkpoint = self.store.blob_file(blob).read_bytes() if blob else None
        keys = [p.key for p in job.spec.parameters]
        opt = self.engine().start_job(self.load_scene(scene, keys), job.spec, refs,
                                      self._read_blob, checkpoint)
        params = {p.key: p
                  for p in self.store.scene_parameters(job.owner, job.spec.scene).parameters}
        run = Run(opt, {k: list(params[k].shape) for k in opt.settings},
                  {k: params[k].kind for k in opt.settings})
        with self._lock:
            if self.store.get_job(job.name).state != pb.QUEUED:
                self._drop(job.name)
                return None
            self._runs[job.name] = run
            job.state = pb.RUNNING
            job.integrator, job.integrator_reason = opt.integrator_name, opt.integrator_reason
            job.sensors_rendered[:] = sorted(refs)
            job.notes[:] = opt.notes
            if job.resumed_from == "pending":
                job.resumed_from = (f"checkpoint at iteration {opt.iteration}" if checkpoint
                                    else "from the start")
            self.store.truncate_history(job.name, opt.iteration)  # they will run again
            self._save(job)
        return run

    def _iterate(self, job: pb.Job, run: Run) -> None:
        opt = run.opt
        step = opt.step()
        stepped = time.perf_counter()
        record = pb.IterationRecord(
            iteration=step.iteration, seconds=opt.elapsed, loss=step.loss,
            parameters=self.engine().values_to_proto(step.values, run.shapes, None),
            errors=[pb.ParameterError(key=k, max_abs=e[0], rmse=e[1], relative=e[2])
                    for k, e in step.errors.items()])
        if step.image_error is not None:
            record.image_error = step.image_error
        self.store.add_iteration(job.name, record)
        with self._lock:
            job.iteration = step.iteration + 1
            job.loss = step.loss
            job.best_iteration, job.best_loss = opt.best.iteration, opt.best.loss
            job.elapsed_seconds = opt.elapsed
            _count_guards(job, opt)
            self.store.put_job(job)
        self._publish(job.name, pb.JobEvent(iteration=record))
        if step.done:
            self._finish(job, run, pb.SUCCEEDED, step.stop_reason, last=step)
            return
        if opt.iteration % CHECKPOINT_EVERY == 0:
            self._checkpoint(job.name, run)
        # Recording and checkpointing are the job's work too: on its clock from the next
        # iteration's time on.
        opt.elapsed += time.perf_counter() - stepped

    def _finish(self, job: pb.Job, run: Run, state: int, reason: str, last=None) -> None:
        opt = run.opt
        history = self.store.history(job.name)
        chosen = []
        if opt.best.iteration >= 0:
            chosen.append((pb.BEST, opt.best.iteration, opt.best.loss, opt.best.values))
        if last is not None:
            chosen.append((pb.LAST, last.iteration, last.loss, last.values))
        elif history:
            h = history[-1]
            chosen.append((pb.LAST, h.iteration, h.loss, opt.values()))
        scene = self.store.get_scene(job.owner, job.spec.scene)
        for res in self.engine().results(opt, job.name, chosen, run.shapes, run.kinds,
                                          self.store.put_blob, scene, self.loadable(scene)):
            self.store.put_result(res)
        notes = self.engine().diagnose(opt, chosen[-1][3] if chosen else {}, history)
        with self._lock:
            self._drop(job.name)
            _count_guards(job, opt)  # diagnose() read the last step's counts
            job.notes.extend(notes)
            job.state, job.stop_reason = state, reason
            self._save(job)

    def _fail(self, job: pb.Job, message: str) -> None:
        with self._lock:
            self._drop(job.name)
            job.state, job.error, job.stop_reason = pb.FAILED, message, "failed"
            self._save(job)

    def _drop(self, name: str) -> None:
        with self._lock:
            self._runs.pop(name, None)
            if name in self._runnable:
                self._runnable.remove(name)

    def _checkpoint(self, name: str, run: Run) -> None:
        self.store.set_checkpoint(name, self.store.put_blob(run.opt.checkpoint()))

    def _read_blob(self, name: str) -> bytes:
        return self.store.blob_file(name).read_bytes()


def _count_guards(job: pb.Job, opt) -> None:
    """The job's guard counters; the latest step's are added at the next read of values."""
    job.nonfinite_gradient_steps = opt.nonfinite_steps
    job.skipped_steps = opt.skipped_steps
    job.clamped_components = opt.clamped


def _offer(queues: list[asyncio.Queue], event: pb.JobEvent) -> None:
    """Queues an event for watchers; a watcher too slow to keep up loses iteration events,
    never state changes (the final one ends its stream)."""
    for q in queues:
        try:
            q.put_nowait(event)
        except asyncio.QueueFull:
            if event.HasField("job"):
                q.get_nowait()
                q.put_nowait(event)
