"""Which worker does what next: a state machine without Mitsuba, threads or I/O.

The runner (``runner.py``) tells it what happens (jobs added, paused, resumed, cancelled;
workers ready or lost; actions done) and asks it, whenever a worker is free, what that worker
does next. Tests drive it directly with a fake clock and no processes.

Decisions, in order, for a free worker:
1. a pause or cancel requested on a job loaded on it (acted on at an iteration boundary);
2. a scene task (load, render, reference check): short, and a user is waiting on each;
3. the job whose slice is running, until ``slice_seconds`` have passed while others wait;
   a job in its end phase (its iterations are over, or it was cancelled) makes its result
   images one sensor per action ("results"), then ends ("finish"): other jobs get their
   slices between, so an end phase of many sensors does not hold a worker for minutes;
4. else the next job by fair share *per user*: the user with the least device time so far
   (a user with ten jobs gets no more than a user with one), then that user's least-served
   job. A user who was idle comes back at the least busy active user's account, not with
   credit saved up. A job loaded elsewhere stays there (its state is never shipped per
   iteration); a job not loaded anywhere goes to the least loaded free worker.

A worker holds at most ``max_resident`` loaded jobs. Switching jobs evicts one (checkpoint and
release, done by the runner) before another loads: every scene a process holds makes every
job's kernels bigger, since Mitsuba dispatches a BSDF's or emitter's virtual call over every
live instance (an iteration of a 64 px Cornell box took 2.4x as long with four other such
scenes alive in the process). Switches are what slices pay for, so a slice is long against a
switch and short against a user's patience (bench/switching.py measures both).
"""

from __future__ import annotations

import collections
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable

SLICE_SECONDS = 2.0   # a job keeps its worker this long while others wait
STEP_SECONDS = 0.25   # one step call: a pause or cancel waits at most this long
MAX_STEP = 1000       # iterations in one step call
EMA = 0.3             # weight of the newest per-iteration time


@dataclass
class Action:
    """What a worker does next. ``kind``: "task", "load", "step" (``n`` iterations), "evict"
    (checkpoint, release; the job waits for its next slice), "park" (checkpoint, release;
    the job is paused), "cancel" (the iterations stop: the end phase begins), "results"
    (the result images of the job's ``n``-th rendered sensor), "finish" (the rest of the
    results, release; the job ends)."""

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
    name: str
    user: str
    worker: str | None = None   # where its run is loaded
    paused: bool = False
    control: str = ""           # "pause" or "cancel", requested while loaded or busy
    started: bool = False       # has run (has a checkpoint or results to make on cancel)
    busy: bool = False          # an action on it is in flight
    per_iteration: float | None = None  # seconds, moving average
    used: float = 0.0           # device seconds so far
    last_run: float = -math.inf
    crashes: list[str] = field(default_factory=list)  # how workers were lost under it
    ending: bool = False        # in its end phase: no more iterations, results to make
    parts: int = 0              # sensors whose result images the end phase renders...
    part: int = 0               # ...and how many of them are done

    @property
    def wants_worker(self) -> bool:
        # A cancelled job, paused or not, still needs a worker to make its results.
        return (not self.paused and self.control != "pause") or self.ending or (
            self.control == "cancel" and self.started)


@dataclass
class Worker:
    name: str
    ready: bool = False
    resident: list[str] = field(default_factory=list)  # least recently run first
    action: Action | None = None
    current: str | None = None  # the job whose slice is running
    slice_start: float | None = None  # None: the current job's slice starts at its next step


@dataclass
class Lost:
    """What a worker's loss did to the job it was running (``job``, or "" for a task)."""

    job: str = ""
    failed: bool = False  # it had already cost a worker: it ends FAILED
    crashes: list[str] = field(default_factory=list)  # each loss under it, in words
    others: list[str] = field(default_factory=list)  # loaded there, to reload elsewhere


class Scheduler:
    def __init__(self, clock: Callable[[], float] = time.monotonic,
                 slice_seconds: float = SLICE_SECONDS, step_seconds: float = STEP_SECONDS,
                 max_resident: int = 1) -> None:
        self.clock = clock
        self.slice_seconds, self.step_seconds = slice_seconds, step_seconds
        self.max_resident = max_resident
        self.jobs: dict[str, Job] = {}
        self.workers: dict[str, Worker] = {}
        self.tasks: collections.deque = collections.deque()
        self.held = False  # nothing starts while set (the daemon cannot record results)
        self.usage: dict[str, float] = collections.defaultdict(float)  # per user
        self.typical: dict[str, float] = {}  # seconds an action of each kind takes (EMA)
        self.served: dict[str, float] = collections.defaultdict(lambda: -math.inf)  # last

    # -- workers ----------------------------------------------------------------------------

    def add_worker(self, name: str) -> None:
        self.workers[name] = Worker(name)

    def remove_worker(self, name: str) -> None:
        """The worker is gone for good (its machine left); call ``worker_lost`` first."""
        self.workers.pop(name, None)

    def worker_ready(self, name: str) -> None:
        self.workers[name].ready = True

    def worker_lost(self, name: str, what: str = "", counts: bool = True) -> Lost:
        """The worker's process is gone: its loaded jobs lose their runs. The one it was
        running is retried once; with ``counts`` (the worker died or hung, rather than being
        stopped on purpose) a second loss under the same job fails it. ``what`` says how it
        was lost, for the job's message."""
        w = self.workers[name]
        lost = Lost()
        action, w.action = w.action, None
        if action is not None:
            self._refund(action)
        for job in [self.jobs[j] for j in w.resident if j in self.jobs]:
            job.worker, job.busy = None, False
            if action is not None and job.name == action.job:
                continue
            lost.others.append(job.name)
        if action is not None and action.job in self.jobs:
            job = self.jobs[action.job]
            job.busy, job.worker = False, None
            lost.job = job.name
            if counts:
                job.crashes.append(what)
                lost.failed = len(job.crashes) >= 2
            lost.crashes = list(job.crashes)
            if lost.failed:
                self.remove(job.name)
        w.ready, w.resident, w.current = False, [], None
        return lost

    # -- jobs -------------------------------------------------------------------------------

    def add_job(self, name: str, user: str, paused: bool = False,
                started: bool = False) -> None:
        self._activate(user)
        self.jobs[name] = Job(name, user, paused=paused, started=started)

    def remove(self, name: str) -> None:
        job = self.jobs.pop(name, None)
        if job is not None and job.worker in self.workers:
            w = self.workers[job.worker]
            if name in w.resident:
                w.resident.remove(name)
            if w.current == name:
                w.current = None

    def pause(self, name: str) -> bool:
        """True when the job is parked now (it was not loaded); else it parks at the next
        iteration boundary of its worker."""
        job = self.jobs[name]
        if job.worker is None and not job.busy:
            job.paused, job.control = True, ""
            return True
        if job.control != "cancel":
            job.control = "pause"
        return False

    def resume(self, name: str) -> None:
        job = self.jobs[name]
        if job.control == "pause":
            job.control = ""  # a pause not yet carried out is withdrawn
        if job.paused:
            self._activate(job.user)
            job.paused = False

    def cancel(self, name: str) -> bool:
        """True when the job can end now, without a worker: it never ran, or it is not loaded
        and has nothing to show. Else a worker loads it (if needed) and finishes it."""
        job = self.jobs[name]
        if job.ending:  # its iterations are over already: the end phase goes on
            return False
        if job.worker is None and not job.busy and not job.started:
            self.remove(name)
            return True
        job.control = "cancel"
        return False

    def end(self, name: str, parts: int) -> None:
        """The job's iterations are over (it ran them all, or a cancel stopped them): what
        is left is its end phase, ``parts`` "results" actions and a "finish"."""
        job = self.jobs[name]
        job.ending, job.parts, job.part = True, parts, 0
        if job.control == "cancel":
            job.control = ""

    def in_flight(self, name: str) -> Action | None:
        """The action running on the job, if any."""
        for w in self.workers.values():
            if w.action is not None and w.action.job == name:
                return w.action
        return None

    # -- tasks ------------------------------------------------------------------------------

    def add_task(self, task: Any) -> None:
        self.tasks.append(task)

    # -- the decision -----------------------------------------------------------------------

    def next(self, worker: str) -> Action | None:
        """What the free ``worker`` does now, or None (it waits for an event)."""
        w = self.workers[worker]
        if not w.ready or w.action is not None or self.held:
            return None
        for name in w.resident:
            job = self.jobs[name]
            if job.control == "cancel" and not job.ending:
                return self._begin(w, Action("cancel", worker, name))
            if job.control == "pause":
                return self._begin(w, Action("park", worker, name))
        if self.tasks:
            return self._begin(w, Action("task", worker, task=self.tasks.popleft()))
        job = self._pick(w)
        if job is None:
            return None
        if job.worker == worker:
            if w.current != job.name or w.slice_start is None or self._expired(w):
                w.current, w.slice_start = job.name, self.clock()  # a new slice
            if job.ending:
                return self._begin(w, Action("results", worker, job.name, n=job.part)
                                   if job.part < job.parts else Action("finish", worker, job.name))
            return self._begin(w, Action("step", worker, job.name, n=self._iterations(job, w)))
        if len(w.resident) >= self.max_resident:
            return self._begin(w, Action("evict", worker, w.resident[0]))
        return self._begin(w, Action("load", worker, job.name))

    def done(self, action: Action, iterations: int = 0, finished: bool = False) -> None:
        """The action completed (``finished``: the job ended with it, whatever its outcome).
        Its time goes to the job's user."""
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
        elif action.kind in ("evict", "park"):
            self._unload(job, w)
            job.started = True
            if action.kind == "park":
                job.paused = True
                if job.control == "pause":  # a cancel that came meanwhile still stands
                    job.control = ""
        if action.kind == "cancel":  # the runner says with ``end`` how many parts follow
            job.ending, job.control = True, ""
        if action.kind == "results":
            job.part += 1
        if finished:
            self.remove(job.name)

    def drop_run(self, action: Action) -> None:
        """The action ended without a record of it, and its job's run was released: the job
        waits to be loaded again from its last checkpoint."""
        w = self.workers[action.worker]
        w.action = None
        self._refund(action)
        job = self.jobs.get(action.job)
        if job is not None:
            job.busy = False
            self._unload(job, w)

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
            by_user[u], key=lambda j: (j.control != "cancel", j.used, j.last_run))]
        ranked.sort(key=lambda j: j.control != "cancel")
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
