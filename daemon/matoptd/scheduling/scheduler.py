"""Which worker does what next, and where each job is in its life: a state machine without
Mitsuba, threads or I/O.

Job control, the lanes and recovery tell it what happens (jobs added, paused, resumed,
cancelled; workers ready or lost; actions done) and ask it, whenever a worker is free, what
that worker does next. It holds each active job's record (``records.JobRecord``) and is the
only code that changes a job's ``Phase``; the others persist the record after each change.
Tests drive it directly with a fake clock and no processes.

    QUEUED --load--> RUNNING --pause--> PAUSING --park--> PAUSED --resume--> QUEUED
       |                |  ^---resume----'                   |
       |                '--cancel--> CANCELLING --cancel action--> ENDING --finish--> outcome
       '--cancel (never ran)--> CANCELLED          last iteration --'
    a lost worker: RUNNING -> QUEUED, PAUSING -> PAUSED; a second loss under a job: FAILED
    the daemon stopping: RUNNING, PAUSING, CANCELLING, ENDING -> INTERRUPTED

Decisions, in order, for a free worker:
1. a pause or cancel requested on a job loaded on it (acted on at an iteration boundary);
2. a scene task (load, render, reference check): short, and a user is waiting on each; a
   task in pieces (a paused job's standard errors on request, up to a minute) is a piece per
   task, each on the worker that holds its run and after another job's turn there, if any;
3. the job whose slice is running, until ``slice_seconds`` have passed while others wait;
   a job in its end phase (its iterations are over, or it was cancelled) makes its result
   images one sensor per action ("results"), estimates its standard errors a step's time per
   action ("estimate"), then ends ("finish"): other jobs get their slices between, so an end
   phase of many sensors, or of a long job's estimate (up to a minute), does not hold a
   worker for minutes;
4. else the next job by fair share *per user*: the user with the least device time so far
   (a user with ten jobs gets no more than a user with one), then that user's least-served
   job. A user who was idle comes back at the least busy active user's account, not with
   credit saved up. A job loaded elsewhere stays there (its state is never shipped per
   iteration); a job not loaded anywhere goes to the least loaded free worker.

A worker holds at most ``max_resident`` loaded jobs. Switching jobs evicts one (checkpoint and
release, done by its lane) before another loads: every scene a process holds makes every
job's kernels bigger, since Mitsuba dispatches a BSDF's or emitter's virtual call over every
live instance (an iteration of a 64 px Cornell box took 2.4x as long with four other such
scenes alive in the process). Switches are what slices pay for, so a slice is long against a
switch and short against a user's patience (bench/switching.py measures both). A job whose
standard errors are under way is not evicted (it would begin them again): the job due loads
beside it, one more for that while; so does a paused job's run while its standard errors
on request are estimated in pieces (the engine loads it; the scheduler does not count it).

``Scheduler`` is over 300 lines: the transitions and the decisions read the same few fields,
and splitting them would put one state machine's rules in two places.
"""

from __future__ import annotations

import collections
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

from ..records import Ending, JobRecord, Phase

SLICE_SECONDS = 2.0   # a job keeps its worker this long while others wait
STEP_SECONDS = 0.25   # one step call: a pause or cancel waits at most this long
MAX_STEP = 1000       # iterations in one step call
EMA = 0.3             # weight of the newest per-iteration time
WANTS_WORKER = frozenset({Phase.QUEUED, Phase.RUNNING, Phase.CANCELLING, Phase.ENDING})
INTERRUPTIBLE = frozenset({Phase.RUNNING, Phase.PAUSING, Phase.CANCELLING, Phase.ENDING})


@dataclass
class Action:
    """What a worker does next. ``kind``: "task", "load", "step" (``n`` iterations), "evict"
    (checkpoint, release; the job waits for its next slice), "park" (checkpoint, release;
    the job is paused), "cancel" (the iterations stop: the end phase begins), "results"
    (the result images of the job's ``n``-th rendered sensor), "estimate" (a piece of its
    standard errors), "finish" (the rest of the results, release; the job ends)."""

    kind: str
    worker: str
    job: str = ""
    n: int = 0
    task: Any = None
    began: float = 0.0
    user: str = ""         # whose job it is
    charged: float = 0.0   # seconds charged to the user when it began (see ``_begin``)


@dataclass
class Job:
    """An active job: its record, and what running it needs besides."""

    record: JobRecord
    worker: str | None = None   # where its run is loaded
    started: bool = False       # has run (has a checkpoint, or results to make on cancel)
    busy: bool = False          # an action on it is in flight
    per_iteration: float | None = None  # seconds, moving average
    used: float = 0.0           # device seconds so far
    last_run: float = -math.inf
    crashes: list[str] = field(default_factory=list)  # how workers were lost under it
    cancel_asked: float | None = None  # when, while its iterations may still keep it waiting
    checkpointed: float = -math.inf    # when its lane last wrote its checkpoint
    queued: float = 0.0         # when it last became QUEUED (the scheduler's clock)

    @property
    def name(self) -> str:
        return self.record.name

    @property
    def user(self) -> str:
        return self.record.owner

    @property
    def phase(self) -> Phase:
        return self.record.phase

    @property
    def wants_worker(self) -> bool:
        return self.record.phase in WANTS_WORKER


@dataclass
class Worker:
    name: str
    ready: bool = False
    resident: list[str] = field(default_factory=list)  # least recently run first
    action: Action | None = None
    current: str | None = None  # the job whose slice is running
    slice_start: float | None = None  # None: the current job's slice starts at its next step
    piece: bool = False  # its last action was a task (a task's next piece waits a turn)


@dataclass
class Lost:
    """What a worker's loss did to the job it was running (``job``, or "" for a task)."""

    job: str = ""
    failed: bool = False  # it had already cost a worker: it ends FAILED
    crashes: list[str] = field(default_factory=list)  # each loss under it, in words
    others: list[str] = field(default_factory=list)  # loaded there, to reload elsewhere


class Observer(Protocol):
    """Told what the scheduler sees happen, for the daemon's metrics; it must not raise."""

    def started(self, job: Job, waited: float) -> None:
        """A worker loaded a QUEUED job, which had waited ``waited`` seconds."""

    def stepped(self, worker: str, iterations: int) -> None:
        """``worker`` ran ``iterations`` of a job."""


class Scheduler:
    def __init__(self, clock: Callable[[], float] = time.monotonic,
                 slice_seconds: float = SLICE_SECONDS, step_seconds: float = STEP_SECONDS,
                 max_resident: int = 1) -> None:
        self.clock = clock
        self.slice_seconds, self.step_seconds = slice_seconds, step_seconds
        self.max_resident = max_resident
        self.jobs: dict[str, Job] = {}
        self.workers: dict[str, Worker] = {}
        self.tasks: collections.deque = collections.deque()  # (worker or None, task)
        self.held = False  # nothing starts while set (the daemon cannot record results)
        self.usage: dict[str, float] = collections.defaultdict(float)  # per user
        self.observer: Observer | None = None
        self.typical: dict[str, float] = {}  # seconds an action of each kind takes (EMA)
        self.served: dict[str, float] = collections.defaultdict(lambda: -math.inf)  # last

    # -- workers ----------------------------------------------------------------------------

    def add_worker(self, name: str) -> None:
        self.workers[name] = Worker(name)

    def remove_worker(self, name: str) -> None:
        """The worker is gone for good (its machine left); call ``worker_lost`` first. The
        pieces of tasks for it go to any worker (where the next piece loads its run again)."""
        self.workers.pop(name, None)
        self.tasks = collections.deque((None if w == name else w, t) for w, t in self.tasks)

    def worker_ready(self, name: str) -> None:
        self.workers[name].ready = True

    def worker_lost(self, name: str, what: str = "", counts: bool = True,
                    requeue: bool = True) -> Lost:
        """The worker's process is gone: its loaded jobs lose their runs and go on from their
        checkpoints (RUNNING ones QUEUED again, with ``requeue``; PAUSING ones PAUSED). The
        one it was running is retried once; with ``counts`` (the worker died or hung, rather
        than being stopped on purpose) a second loss under the same job fails it. ``what``
        says how it was lost, for the job's message."""
        w = self.workers[name]
        lost = Lost()
        action, w.action = w.action, None
        if action is not None:
            self._refund(action)
        for job in [self.jobs[j] for j in w.resident if j in self.jobs]:
            self._lose_run(job, requeue)
            if action is None or job.name != action.job:
                lost.others.append(job.name)
        if action is not None and action.job in self.jobs:
            job = self.jobs[action.job]
            self._lose_run(job, requeue)
            lost.job = job.name
            if counts:
                job.crashes.append(what)
                lost.failed = len(job.crashes) >= 2
            lost.crashes = list(job.crashes)
            if lost.failed:
                self.remove(job.name)
        w.ready, w.resident, w.current = False, [], None
        return lost

    def _lose_run(self, job: Job, requeue: bool) -> None:
        job.worker, job.busy = None, False
        if job.phase is Phase.PAUSING:
            job.record.phase = Phase.PAUSED
        elif job.phase is Phase.RUNNING and requeue:
            job.record.phase, job.queued = Phase.QUEUED, self.clock()

    # -- jobs -------------------------------------------------------------------------------

    def add_job(self, record: JobRecord, started: bool = False) -> Job:
        """A job that is QUEUED (new, resumed), or PAUSED or INTERRUPTED (to be cancelled)."""
        self._activate(record.owner)
        job = self.jobs[record.name] = Job(record, started=started, queued=self.clock())
        return job

    def remove(self, name: str) -> None:
        job = self.jobs.pop(name, None)
        if job is not None and job.worker in self.workers:
            self._unload(job, self.workers[job.worker])

    def pause(self, name: str) -> bool:
        """True when the job is PAUSED now (it was not loaded); else it is PAUSING and parks
        at its worker's next iteration boundary. A job whose iterations stop anyway (it is
        cancelling or ending) is left to end."""
        job = self.jobs[name]
        if job.phase not in (Phase.QUEUED, Phase.RUNNING):
            return job.phase is Phase.PAUSED
        if job.worker is None and not job.busy:
            job.record.phase = Phase.PAUSED
            return True
        job.record.phase = Phase.PAUSING
        return False

    def resume(self, name: str) -> None:
        """A pause not yet carried out is withdrawn; a paused (or interrupted) job queues."""
        job = self.jobs[name]
        if job.phase is Phase.PAUSING:
            job.record.phase = Phase.RUNNING
        elif job.phase in (Phase.PAUSED, Phase.INTERRUPTED):
            self._activate(job.user)
            job.record.phase, job.queued = Phase.QUEUED, self.clock()

    def cancel(self, name: str) -> bool:
        """True when the job is CANCELLED now, without a worker: it never ran and is not
        loaded. Else it is CANCELLING: a worker loads it (if need be) and ends it."""
        job = self.jobs[name]
        if job.phase in (Phase.CANCELLING, Phase.ENDING):
            return False
        if job.worker is None and not job.busy and not job.started:
            self.remove(name)
            job.record.phase, job.record.stop_reason = Phase.CANCELLED, "cancelled"
            return True
        job.record.phase = Phase.CANCELLING
        job.cancel_asked = self.clock()
        return False

    def end(self, name: str, outcome: Phase, reason: str, parts: int) -> None:
        """The job's iterations are over (it ran them all, or a cancel stopped them), whatever
        was asked of it meanwhile: its end phase is ``parts`` "results" actions, "estimate"
        actions until the standard errors are done (none without a result: ``parts`` 0) and a
        "finish", after which it is ``outcome``."""
        job = self.jobs[name]
        job.record.phase = Phase.ENDING
        job.record.ending = Ending(outcome, reason, parts)
        job.cancel_asked = None  # result renders are not cut off

    def finish(self, name: str) -> None:
        """The end phase is over: the job is its outcome, and leaves the scheduler."""
        record = self.jobs[name].record
        ending, record.ending = record.ending, None
        record.phase, record.stop_reason = ending.outcome, ending.reason
        self.remove(name)

    def cut_off(self, name: str) -> None:
        """A cancel stopped the job's worker in the middle of an iteration: the job is
        CANCELLED now, with what its finished iterations reported (``Recovery.cut_off``)."""
        record = self.jobs[name].record
        record.phase, record.stop_reason, record.ending = Phase.CANCELLED, "cancelled", None
        self.remove(name)

    def fail(self, record: JobRecord, message: str) -> None:
        record.phase, record.error, record.stop_reason = Phase.FAILED, message, "failed"
        record.ending = None
        self.remove(record.name)

    def interrupt(self, record: JobRecord, why: str) -> None:
        """The daemon stops (or stopped) while the job ran: INTERRUPTED, resumed on request."""
        cp = record.checkpoint
        record.phase, record.ending = Phase.INTERRUPTED, None
        record.stop_reason = (f"{why}; resume continues from the checkpoint at iteration {cp}"
                              if cp is not None else why)
        self.remove(record.name)

    def late_cancels(self, grace: float) -> list[str]:
        """Workers whose action keeps a cancel waiting longer than ``grace`` seconds."""
        now = self.clock()
        return [w.name for w in self.workers.values() if w.action is not None
                and (job := self.jobs.get(w.action.job)) is not None
                and job.cancel_asked is not None and now - job.cancel_asked > grace]

    def in_flight(self, name: str) -> Action | None:
        """The action running on the job, if any."""
        for w in self.workers.values():
            if w.action is not None and w.action.job == name:
                return w.action
        return None

    # -- tasks ------------------------------------------------------------------------------

    def add_task(self, task: Any, worker: str | None = None) -> None:
        """A task for any worker, or a piece of one for ``worker`` (which holds its run)."""
        self.tasks.append((worker, task))

    def _task(self, w: Worker) -> Any:
        """The next task ``w`` takes: any worker's first; a piece for it after a job's turn
        (when a job wants it), so that a task of many pieces does not hold it."""
        for n, (worker, task) in enumerate(self.tasks):
            if worker is None or (worker == w.name and (not w.piece or self._pick(w) is None)):
                del self.tasks[n]
                w.piece = True
                return task
        return None

    # -- the decision -----------------------------------------------------------------------

    def next(self, worker: str) -> Action | None:
        """What the free ``worker`` does now, or None (it waits for an event)."""
        w = self.workers[worker]
        if not w.ready or w.action is not None or self.held:
            return None
        for name in w.resident:
            job = self.jobs[name]
            if job.phase is Phase.CANCELLING:
                return self._begin(w, Action("cancel", worker, name))
            if job.phase is Phase.PAUSING:
                return self._begin(w, Action("park", worker, name))
        task = self._task(w)
        if task is not None:
            return self._begin(w, Action("task", worker, task=task))
        job = self._pick(w)
        if job is None:
            return None
        w.piece = False
        if job.worker == worker:
            if w.current != job.name or w.slice_start is None or self._expired(w):
                w.current, w.slice_start = job.name, self.clock()  # a new slice
            ending = job.record.ending
            if job.phase is Phase.ENDING and ending is not None:
                return self._begin(w, Action(ending.next, worker, job.name, n=ending.done))
            return self._begin(w, Action("step", worker, job.name, n=self._iterations(job, w)))
        # A job estimating its standard errors stays: evicted, it would begin them again.
        # The job due loads beside it (the worker holds one more for that while).
        evictable = [n for n in w.resident if not _estimating(self.jobs[n])]
        if len(w.resident) >= self.max_resident and evictable:
            return self._begin(w, Action("evict", worker, evictable[0]))
        return self._begin(w, Action("load", worker, job.name))

    def done(self, action: Action, iterations: int = 0, estimated: bool = False) -> None:
        """The action completed (a "finish" ends its job; an "estimate" says whether the
        standard errors are ``estimated``). Its time goes to the job's user; a job removed
        meanwhile (failed, deleted) only frees the worker."""
        w = self.workers[action.worker]
        w.action = None
        seconds = self.clock() - action.began
        self._refund(action)
        if action.kind != "step":
            t = self.typical.get(action.kind)
            self.typical[action.kind] = seconds if t is None else EMA * seconds + (1 - EMA) * t
        job = self.jobs.get(action.job)
        if job is None:
            return
        job.busy = False
        self.usage[job.user] += seconds
        job.used += seconds
        job.last_run = self.served[job.user] = self.clock()
        if action.kind == "step" and iterations:
            if self.observer is not None:
                self.observer.stepped(w.name, iterations)
            rate = seconds / iterations
            job.per_iteration = rate if job.per_iteration is None else (
                EMA * rate + (1 - EMA) * job.per_iteration)
            job.started = True
        if action.kind == "load":
            # A job just loaded gets its slice whatever the load cost: evicting it before it
            # stepped would waste the load.
            job.worker = w.name
            w.resident.append(job.name)
            w.current, w.slice_start = job.name, None
            if job.record.ending is not None:  # a run of its own: its standard errors anew
                job.record.ending.estimated = False
            if job.phase is Phase.QUEUED:
                job.record.phase = Phase.RUNNING
                if self.observer is not None:
                    self.observer.started(job, self.clock() - job.queued)
        elif action.kind in ("evict", "park"):
            self._unload(job, w)
            job.started = True
            if action.kind == "park" and job.phase is Phase.PAUSING:
                job.record.phase = Phase.PAUSED  # (a cancel that came meanwhile still stands)
        elif action.kind == "results" and job.record.ending is not None:
            job.record.ending.done += 1
        elif action.kind == "estimate" and job.record.ending is not None:
            job.record.ending.estimated = estimated
        elif action.kind == "finish":
            self.finish(job.name)

    def drop_run(self, action: Action) -> None:
        """The action ended without a record of it, and its job's run was released: the job
        waits to be loaded again from its last checkpoint (PAUSING: it is PAUSED)."""
        w = self.workers[action.worker]
        w.action = None
        self._refund(action)
        job = self.jobs.get(action.job)
        if job is not None:
            job.busy = False
            self._unload(job, w)
            if job.phase is Phase.PAUSING:
                job.record.phase = Phase.PAUSED

    # -- inside -----------------------------------------------------------------------------

    def _begin(self, w: Worker, action: Action) -> Action:
        """Starts the action and charges its user what it is expected to cost now, not when
        it is done: decisions taken meanwhile (every free worker asks at once when many jobs
        arrive) must see that user's account as already drawn on, or they all pick the same
        user. ``done`` replaces the estimate with the real time."""
        action.began = self.clock()
        w.action = action
        if action.job:
            job = self.jobs[action.job]
            job.busy = True
            action.user = job.user
            action.charged = (action.n * job.per_iteration
                              if action.kind == "step" and job.per_iteration
                              else self.typical.get(action.kind, self.step_seconds))
            self.usage[job.user] += action.charged
            if action.job in w.resident:  # most recently run last
                w.resident.remove(action.job)
                w.resident.append(action.job)
        return action

    def _refund(self, action: Action) -> None:
        if action.user:
            self.usage[action.user] -= action.charged
            action.charged = 0.0

    def _unload(self, job: Job, w: Worker) -> None:
        job.worker = None
        if job.name in w.resident:
            w.resident.remove(job.name)
        if w.current == job.name:
            w.current = None

    def _activate(self, user: str) -> None:
        """A user with nothing to run comes back at the least busy active user's account: no
        credit saved up while away, no debt either."""
        active = {j.user for j in self.jobs.values() if j.wants_worker}
        if user not in active and active:
            self.usage[user] = max(self.usage[user], min(self.usage[u] for u in active))

    def _candidates(self, w: Worker) -> list[Job]:
        return [j for j in self.jobs.values()
                if j.wants_worker and not j.busy and j.worker in (None, w.name)]

    def _pick(self, w: Worker) -> Job | None:
        candidates = self._candidates(w)
        if not candidates:
            return None
        current = self.jobs.get(w.current) if w.current else None
        if current in candidates and (not self._expired(w) or len(candidates) == 1):
            return current
        by_user: dict[str, list[Job]] = collections.defaultdict(list)
        for j in candidates:
            by_user[j.user].append(j)
        # Cancels first (a user is waiting on the results), then fair share; between users
        # with the same account, the one served longest ago.
        order = sorted(by_user, key=lambda u: (self.usage[u], self.served[u]))
        ranked = [j for u in order for j in sorted(
            by_user[u], key=lambda j: (j.phase is not Phase.CANCELLING, j.used, j.last_run))]
        ranked.sort(key=lambda j: j.phase is not Phase.CANCELLING)
        for job in ranked:
            if job.worker == w.name or not self._better_placed(job, w):
                return job
        return current if current in candidates else None

    def _expired(self, w: Worker) -> bool:
        return w.slice_start is not None and self.clock() - w.slice_start >= self.slice_seconds

    def _better_placed(self, job: Job, w: Worker) -> bool:
        """Whether another free worker is less loaded than ``w`` for a job to be loaded."""
        mine = len(w.resident)
        return any(o is not w and o.ready and o.action is None and len(o.resident) < mine
                   for o in self.workers.values())

    def _iterations(self, job: Job, w: Worker) -> int:
        """Iterations for one step call: about ``step_seconds`` of work, within the slice when
        others wait."""
        if job.per_iteration is None or job.per_iteration <= 0:
            return 1
        budget = self.step_seconds
        if len(self._candidates(w)) > 1 and w.slice_start is not None:
            left = self.slice_seconds - (self.clock() - w.slice_start)
            budget = min(budget, max(left, job.per_iteration))
        return max(1, min(MAX_STEP, int(budget / job.per_iteration)))


def _estimating(job: Job) -> bool:
    """Whether the job's end phase is on its standard errors (its result images made)."""
    e = job.record.ending
    return job.phase is Phase.ENDING and e is not None and e.next == "estimate"
