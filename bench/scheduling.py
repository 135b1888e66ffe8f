"""Scheduling: the scheduler alone, with many users, jobs and workers, in simulated time.

What it models. ``matoptd.scheduling.scheduler.Scheduler`` (the real class) decides for every
free worker what it does next; here fake workers "run" each action by letting simulated time
pass, in a discrete-event simulation: an event queue of actions in flight, ordered by when
they end, and a simulated clock handed to ``Scheduler(clock=...)``. The calls mirror the
lanes (``scheduling/lanes.py``: ``Lane.run``, ``_next``, ``do``, ``_load``, ``_step``,
``_evict``, ``_finish``): every worker asks ``next()`` when free; a load, an evict or a step
ends with ``done(action)`` (a step with its iterations); the step that reaches a job's
iteration budget also makes the job's results in the same call and ends the job (``end``,
then ``finish``: the daemon's end phase, a "results" action per sensor and a "finish", is
modelled as one cost); and, as the lanes' ``notify_all`` wakes every waiting lane after each
``done``, every idle
worker asks ``next()`` again after each completed action. Simulated costs: a load 0.5 s, an
evict 0.2 s, a job's results 0.3 s, a step ``n`` iterations at the job's own cost per
iteration (0.05 to 0.5 s), each +-10 % noise (which also keeps workers from finishing in
lockstep). The scheduler picks ``n`` from its own per-iteration estimate, as in the daemon.

The workload (seeded): 1,000 jobs of 50 users, deliberately lopsided: a fifth of the users
have 1 or 2 jobs, a fifth about 70 each, the rest about 9. Every user has about the same
amount of work in all (1 to 3 times a base), so a user with one job has one long job and a
user with 70 has many short ones, and no user runs out of work long before the others: the
question is whether the user with 70 jobs gets 70 times the worker time (per-job fairness)
or the same as the user with one (per-user fairness, what the scheduler promises).

Reported, at 8, 64 and 512 workers, several seeds each:
- dispatch latency: the real wall time (``time.perf_counter``) of each ``next()`` call that
  handed out an action, p50 / p99 / max (target p99 < 10 ms at 64 workers). It runs under the
  lanes' lock, so it delays every lane. Calls that found nothing to do (an idle worker
  woken by someone else's ``done``) are counted apart (most of them estimated rather than
  made: see ``Simulation.wake``); so is the scheduler's whole time (``next`` and ``done``)
  per simulated second: the share of one core it would take at the simulated pace, which
  must stay well below 1;
- fair share: over the backlogged period (from the start until the first user has no work
  left, while every user competes), each user's worker time (loads, steps, evicts, results:
  everything the scheduler charges to the user) against its fair share, max over users of
  ``|share / fair - 1|`` (target <= 10 %). The fair share is max-min fair (water-filling):
  at each instant the busy workers are split equally among the users, except that a user
  with ``k`` unfinished jobs can use at most ``k`` workers (a job runs on one worker at a
  time) and what it cannot use goes to the others, integrated over the period. While every
  user has more jobs than its equal split (8 workers) this is exactly busy worker time /
  number of users; with 64 or 512 workers a user with one job cannot use 1.28 or 10 workers,
  and counting that as unfairness would measure the workload, not the scheduler. At 512
  workers the period is short (the users with many short jobs use up their work on 10
  workers each within a few slices), so there the figure weighs mostly the start;
- makespan: simulated time until the last job ended, against a lower bound (the jobs'
  iterations spread evenly over the workers, or the longest job alone).

What it leaves out: Ray, the daemon, Mitsuba, gRPC, the store; scene tasks, pauses, cancels,
lost workers; the lanes' periodic checkpoints during steps, and their 1 s poll of idle lanes
(nothing changes between events, so that poll would find what the last wake found). All
jobs arrive at time 0 (a burst, as after a daemon restart with a full queue). Latency is
measured in this process with the simulation's own bookkeeping around it, on a machine shared
with others: noise only adds to it.
"""

from __future__ import annotations

import heapq
import random
import statistics
import sys
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field

import common
from common import Result, Settings, Target
from matoptd.records import JobRecord, Phase
from matoptd.scheduling.scheduler import SLICE_SECONDS, STEP_SECONDS, Action, Scheduler
from matoptd.settings import JobSettings, SceneInput

NEEDS_DAEMON = False       # run.py: a pure simulation, no matoptd to start
SETTINGS = JobSettings(SceneInput("", "", {}, {}, ""), [], [])  # no job here ever loads

LOAD, EVICT, RESULTS = 0.5, 0.2, 0.3  # simulated seconds
ITERATION = (0.05, 0.5)    # simulated seconds per iteration, a job's own (log-uniform)
NOISE = 0.10               # +- on every action's cost
WORK_PER_USER = (1.0, 3.0)  # a user's total work, times Size.base_work
TARGET_P99_MS = 10.0       # at 64 workers
TARGET_SHARE = 0.10        # max |share / fair - 1|


@dataclass(frozen=True)
class Size:
    jobs: int
    users: int
    workers: list[int]
    seeds: list[int]
    base_work: float       # simulated seconds of work per user, times WORK_PER_USER


# The base work sets how long every user stays backlogged (at 8 workers, each of the 50 users
# gets a slice about every 50 / 8 slices: the period must hold many) and also the run time:
# every step is a next() call that scans all jobs (about 0.6 ms at 1,000 jobs), so the full
# size is as long as fits in about 2 minutes on 2 cores.
FULL = Size(1000, 50, [8, 64, 512], [1, 2, 3], 36.0)
QUICK = Size(200, 50, [8, 64], [1], 15.0)


# ---------------------------------------------------------------------------------------------
# The workload
# ---------------------------------------------------------------------------------------------


@dataclass
class SimJob:
    name: str
    user: str
    iterations: int        # its budget: it ends after this many
    cost: float            # simulated seconds per iteration
    left: int = 0

    def __post_init__(self) -> None:
        self.left = self.iterations


def job_counts(jobs: int, users: int, rng: random.Random) -> list[int]:
    """Jobs per user, summing to ``jobs``: a fifth of the users with 1 or 2, a fifth heavy
    (about 7 times as many as the rest), the others in between (at least 1 each)."""
    light = users // 5
    counts = [rng.randint(1, 2) for _ in range(light)]
    weights = [rng.uniform(6, 9) if i < light else rng.uniform(0.5, 1.5)
               for i in range(users - light)]
    rest = jobs - sum(counts)
    shares = [max(1, int(rest * w / sum(weights))) for w in weights]
    heavy = max(range(len(shares)), key=shares.__getitem__)
    shares[heavy] += rest - sum(shares)  # what rounding left over (or took too much)
    counts += shares
    rng.shuffle(counts)
    return counts


def workload(size: Size, rng: random.Random) -> list[SimJob]:
    """The jobs, in the (shuffled) order they are submitted."""
    jobs: list[SimJob] = []
    for u, count in enumerate(job_counts(size.jobs, size.users, rng)):
        user = f"user{u:02d}"
        total = size.base_work * rng.uniform(*WORK_PER_USER)
        weights = [rng.uniform(0.5, 1.5) for _ in range(count)]
        for k, w in enumerate(weights):
            cost = _log_uniform(rng, *ITERATION)
            work = total * w / sum(weights)
            jobs.append(SimJob(f"{user}-job{k:02d}", user, max(1, round(work / cost)), cost))
    rng.shuffle(jobs)
    return jobs


def _log_uniform(rng: random.Random, lo: float, hi: float) -> float:
    return lo * (hi / lo) ** rng.random()


# ---------------------------------------------------------------------------------------------
# The simulation
# ---------------------------------------------------------------------------------------------


class Clock:
    """Simulated seconds, set by the event loop; the scheduler only reads it."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@dataclass
class InFlight:
    action: Action
    iterations: int = 0    # a step's iterations as run (the budget may end it early)
    finished: bool = False


@dataclass
class Run:
    """What one simulation measured."""

    workers: int
    seed: int
    decisions: list[float] = field(default_factory=list)  # next() -> action, wall seconds
    polls: list[float] = field(default_factory=list)      # next() -> None, asked, seconds
    polls_counted: float = 0.0  # next() -> None not asked: seconds, estimated (see wake)
    polls_skipped: int = 0
    done_calls: list[float] = field(default_factory=list)  # done(), wall seconds
    spans: list[tuple[str, float, float]] = field(default_factory=list)  # user, start, end
    fair: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    jobs: Counter = field(default_factory=Counter)  # per user
    backlog_end: float = 0.0
    makespan: float = 0.0
    work: float = 0.0      # simulated seconds of all actions together
    kinds: Counter = field(default_factory=Counter)

    def shares(self) -> dict[str, float]:
        """Each user's worker time within the backlogged period."""
        got: dict[str, float] = defaultdict(float)
        for user, start, end in self.spans:
            got[user] += max(0.0, min(end, self.backlog_end) - start)
        return got

    def deviation(self) -> float:
        """max over users of |share / fair - 1| in the backlogged period."""
        got = self.shares()
        return max(abs(got[u] / f - 1) for u, f in self.fair.items() if f > 0)

    def lock_load(self) -> float:
        """The scheduler's wall time (every next() and done()) per simulated second: the
        share of one core it takes, under the lanes' lock, at the simulated pace."""
        busy = (sum(self.decisions) + sum(self.polls) + self.polls_counted
                + sum(self.done_calls))
        return busy / self.makespan


def water_fill(capacity: float, caps: dict[str, int]) -> dict[str, float]:
    """Max-min fair split of ``capacity`` workers among users each able to use at most its
    cap: the smallest caps are filled first, the rest shared equally."""
    out, left, users = {}, capacity, sorted(caps, key=caps.get)
    for i, u in enumerate(users):
        out[u] = min(caps[u], left / (len(users) - i))
        left -= out[u]
    return out


class Simulation:
    SAMPLE = 4  # idle lanes asked after the first one that found nothing (see wake)

    def __init__(self, jobs: list[SimJob], workers: int, seed: int) -> None:
        self.rng = random.Random(seed * 7919 + workers)  # the noise; the workload has its own
        self.clock = Clock()
        self.s = Scheduler(clock=self.clock)
        self.jobs = {j.name: j for j in jobs}
        self.unfinished = Counter(j.user for j in jobs)
        self.run = Run(workers, seed, jobs=Counter(j.user for j in jobs))
        self.events: list[tuple[float, int, str]] = []  # end time, tie-break, worker
        self.flying: dict[str, InFlight] = {}
        self.idle: dict[str, None] = {}  # waiting lanes, in the order they began to wait
        self.seq = 0
        self.rates: dict[str, float] | None = None  # fair workers per user now; None: stale
        self.since = 0.0  # fair shares integrated up to here
        for i in range(workers):
            self.s.add_worker(f"w{i:03d}")
            self.s.worker_ready(f"w{i:03d}")
        for j in jobs:
            self.s.add_job(JobRecord(j.name, j.user, "scenes/sim", SETTINGS))

    def simulate(self) -> Run:
        for w in list(self.s.workers):  # every lane starts: all ask at time 0
            self.dispatch(w)
        while self.events:
            t, _, w = heapq.heappop(self.events)
            self.advance(t)
            self.complete(w)
            self.dispatch(w)  # the lane that finished asks first, then the woken ones
            self.wake()
        if self.s.jobs or any(j.left for j in self.jobs.values()):
            raise RuntimeError(f"{len(self.s.jobs)} job(s) never finished: the scheduler "
                               "left work undone with workers idle")
        self.run.makespan = self.clock.t
        return self.run

    def wake(self) -> None:
        """Every idle lane asks again, as the lanes' ``notify_all`` after a ``done`` makes
        it. An idle worker holds no job here (a loaded job always wants its next step), and
        for a worker holding none ``next()`` depends only on the jobs, not on which worker
        asks, and changes nothing when it finds nothing: once one such lane found nothing,
        the others would too. So only ``SAMPLE`` more are asked (timed) and the rest are
        counted at their mean time: with 512 workers in the tail, asking every one would be
        millions of calls that tell nothing new (and take minutes)."""
        empty: list[float] = []
        for w in list(self.idle):
            worker = self.s.workers[w]
            if len(empty) > self.SAMPLE and not worker.resident and worker.current is None:
                self.run.polls_skipped += 1
                self.run.polls_counted += statistics.fmean(empty)
                continue
            if self.dispatch(w) is None:
                empty.append(self.run.polls[-1])
            elif empty:
                raise RuntimeError(f"{w} got work after an empty worker found none: the "
                                   "shortcut in wake() does not hold")

    def advance(self, t: float) -> None:
        """Moves the clock to ``t``, integrating the fair shares on the way while every
        user still has work (the backlogged period)."""
        if not self.run.backlog_end:
            if self.rates is None:
                self.rates = water_fill(len(self.flying), dict(self.unfinished))
            for u, r in self.rates.items():
                self.run.fair[u] += r * (t - self.since)
            self.since = t
        self.clock.t = t

    def dispatch(self, worker: str) -> Action | None:
        """The worker's ``next()``, timed; what it returns starts now, in simulated time."""
        began = time.perf_counter()
        action = self.s.next(worker)
        wall = time.perf_counter() - began
        if action is None:
            self.run.polls.append(wall)
            self.idle[worker] = None
            return None
        self.run.decisions.append(wall)
        self.idle.pop(worker, None)
        self.run.kinds[action.kind] += 1
        flying = InFlight(action)
        seconds = self.cost(flying)
        self.flying[worker] = flying
        self.rates = None  # one more worker busy
        self.seq += 1
        heapq.heappush(self.events, (self.clock.t + seconds, self.seq, worker))
        self.run.spans.append((self.jobs[action.job].user, self.clock.t,
                               self.clock.t + seconds))
        self.run.work += seconds
        return action

    def cost(self, flying: InFlight) -> float:
        """Simulated seconds of the action; a step also settles how many iterations it runs
        and whether it is the job's last (then the results are made in the same call, as
        the daemon's end phase follows the last step: modelled as one cost)."""
        action, noise = flying.action, self.rng.uniform(1 - NOISE, 1 + NOISE)
        if action.kind == "load":
            return LOAD * noise
        if action.kind in ("evict", "park"):
            return EVICT * noise
        if action.kind != "step":
            raise RuntimeError(f"unexpected action {action.kind}: nothing here asks for it")
        job = self.jobs[action.job]
        flying.iterations = min(action.n, job.left)
        flying.finished = flying.iterations == job.left
        results = RESULTS if flying.finished else 0.0
        return (flying.iterations * job.cost + results) * noise

    def complete(self, worker: str) -> None:
        """The worker's action ended now: ``done`` as a lane calls it."""
        flying = self.flying.pop(worker)
        self.rates = None
        action = flying.action
        began = time.perf_counter()
        self.s.done(action, iterations=flying.iterations)
        if flying.finished:  # its results were made in the same call (see ``cost``)
            self.s.end(action.job, Phase.SUCCEEDED, "iterations", 0)
            self.s.finish(action.job)
        self.run.done_calls.append(time.perf_counter() - began)
        if action.kind != "step":
            return
        job = self.jobs[action.job]
        job.left -= flying.iterations
        if flying.finished:
            self.unfinished[job.user] -= 1
            if not self.unfinished[job.user]:
                del self.unfinished[job.user]
                if not self.run.backlog_end:
                    self.run.backlog_end = self.clock.t  # the first user is out of work


def simulate(size: Size, workers: int, seed: int) -> Run:
    """One run: the seed's workload (the same at every worker count) on ``workers``."""
    return Simulation(workload(size, random.Random(seed)), workers, seed).simulate()


# ---------------------------------------------------------------------------------------------
# The case
# ---------------------------------------------------------------------------------------------


def ms(seconds: float) -> float:
    return seconds * 1000


def lower_bound(jobs: list[SimJob], work: float, workers: int) -> float:
    """No schedule ends sooner: the work spread evenly over the workers, or the longest job
    (one load, its steps and its results, on one worker)."""
    longest = max(LOAD + j.iterations * j.cost + RESULTS for j in jobs)
    return max(work / workers, longest)


def burst(run: Run) -> tuple[int, int]:
    """At time 0 every worker asks at once, before any action is done: how many users the
    first actions went to, and the most workers one user got."""
    first = Counter(user for user, start, _ in run.spans if start == 0.0)
    return len(first), max(first.values(), default=0)


def row(run: Run, bound: float) -> dict:
    d = run.decisions
    users, most = burst(run)
    return {
        "workers": run.workers, "seed": run.seed, "jobs": sum(run.jobs.values()),
        "users": len(run.jobs), "decisions": len(d),
        "next_p50_ms": ms(common.percentile(d, 50)), "next_p99_ms": ms(common.percentile(d, 99)),
        "next_max_ms": ms(max(d)),
        "idle_asks": len(run.polls) + run.polls_skipped, "idle_asks_timed": len(run.polls),
        "idle_ask_p99_ms": ms(common.percentile(run.polls, 99)) if run.polls else 0.0,
        "done_p99_ms": ms(common.percentile(run.done_calls, 99)),
        "scheduler_core_share": run.lock_load(),
        "decisions_wall_s": sum(d), "idle_asks_wall_s": sum(run.polls) + run.polls_counted,
        "done_wall_s": sum(run.done_calls),
        "backlog_end_s": run.backlog_end, "worst_share_deviation": run.deviation(),
        "users_at_time_0": users, "most_workers_one_user_at_time_0": most,
        "makespan_s": run.makespan, "makespan_lower_bound_s": bound, "work_s": run.work,
        **{f"{kind}s": n for kind, n in sorted(run.kinds.items())},
    }


def user_rows(run: Run) -> list[dict]:
    got = run.shares()
    return [{"workers": run.workers, "seed": run.seed, "user": u, "jobs": run.jobs[u],
             "worker_seconds": got[u], "fair_seconds": f, "share_over_fair": got[u] / f}
            for u, f in sorted(run.fair.items())]


def run(settings: Settings, server: object = None) -> Result:
    began = time.perf_counter()
    size = QUICK if settings.quick else FULL
    runs: dict[int, list[Run]] = defaultdict(list)
    rows, users = [], []
    for seed in size.seeds:
        jobs = workload(size, random.Random(seed))
        for workers in size.workers:
            t0 = time.perf_counter()
            # A fresh copy of the same workload each time: the simulation uses it up.
            r = Simulation(workload(size, random.Random(seed)), workers, seed).simulate()
            runs[workers].append(r)
            rows.append(row(r, lower_bound(jobs, sum(j.iterations * j.cost for j in jobs),
                                           workers)))
            users += user_rows(r)
            print(f"bench: scheduling {workers} workers, seed {seed}: {rows[-1]['decisions']} "
                  f"decisions, deviation {r.deviation():.3f}, "
                  f"{time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    files = [common.write_csv(settings.out / "scheduling.csv", rows),
             common.write_csv(settings.out / "scheduling_users.csv", users)]
    return Result("scheduling", "Scheduling: the scheduler alone, simulated",
                  targets(size, runs), lines(size, runs, rows), files,
                  time.perf_counter() - began)


def idle_part(row: dict) -> float:
    """The share of the scheduler's time spent answering idle lanes that nothing waits for."""
    total = row["decisions_wall_s"] + row["idle_asks_wall_s"] + row["done_wall_s"]
    return row["idle_asks_wall_s"] / total


def pooled(rs: list[Run]) -> list[float]:
    """Every decision's latency of these runs (the seeds of one worker count)."""
    return [x for r in rs for x in r.decisions]


def targets(size: Size, runs: dict[int, list[Run]]) -> list[Target]:
    out = []
    for workers, rs in runs.items():
        p99 = ms(common.percentile(pooled(rs), 99))
        out.append(Target(f"next() p99, {size.jobs} jobs on {workers} workers",
                          f"{p99:.2f} ms (target < {TARGET_P99_MS:g} ms)", p99 < TARGET_P99_MS))
    for workers, rs in runs.items():
        devs = [r.deviation() for r in rs]
        out.append(Target(
            f"worst user's |share / fair share - 1| while all {size.users} users are "
            f"backlogged, {workers} workers (median over seeds)",
            f"{common.spread([100 * d for d in devs], '{:.1f} %')} (target <= "
            f"{100 * TARGET_SHARE:g} %)", common.median(devs) <= TARGET_SHARE))
    loads = {w: common.median([r.lock_load() for r in rs]) for w, rs in runs.items()}
    out.append(Target("scheduler's time (next, done) per simulated second: share of one core "
                      "under the lanes' lock (no target)",
                      ", ".join(f"{w} workers {x:.2f}" for w, x in loads.items()), None))
    return out


def lines(size: Size, runs: dict[int, list[Run]], rows: list[dict]) -> list[str]:
    counts = sorted(next(iter(runs.values()))[0].jobs.values())
    out = [
        f"A discrete-event simulation of `matoptd.scheduling.scheduler.Scheduler` with fake "
        f"workers in simulated time: {size.jobs} jobs of {size.users} users (jobs per user "
        f"{counts[0]} to {counts[-1]}, median {common.median(counts):g}; every user "
        f"{WORK_PER_USER[0] * size.base_work:g} to {WORK_PER_USER[1] * size.base_work:g} s of "
        f"work in all), {ITERATION[0]:g} to {ITERATION[1]:g} s per iteration, load "
        f"{LOAD:g} s, evict {EVICT:g} s, results {RESULTS:g} s (+-{NOISE:.0%}); slice "
        f"{SLICE_SECONDS:g} s, step {STEP_SECONDS:g} s; all jobs queued at time 0; seeds "
        f"{', '.join(map(str, size.seeds))}. next() is timed in wall time; the fair share is "
        "max-min (a user cannot use more workers than it has unfinished jobs) over the "
        "backlogged period (until the first user runs out of work).",
        "",
        "| workers | next() p50 / p99 / max, ms | idle asks per decision | scheduler's core "
        "share (idle asks' part) | worst share deviation, % median [min-max] | backlogged "
        "period, s (fair worker time per user) | makespan, s (lower bound) |",
        "|---|---|---|---|---|---|---|",
    ]
    for workers, rs in runs.items():
        mine = [r for r in rows if r["workers"] == workers]
        d = pooled(rs)
        devs = [100 * r.deviation() for r in rs]
        out.append(
            f"| {workers} | {ms(common.percentile(d, 50)):.2f} / "
            f"{ms(common.percentile(d, 99)):.2f} / {ms(max(d)):.1f} | "
            f"{sum(x['idle_asks'] for x in mine) / len(d):.1f} | "
            f"{common.median([r.lock_load() for r in rs]):.2f} "
            f"({common.median([idle_part(x) for x in mine]):.0%}) | "
            f"{common.median(devs):.1f} [{min(devs):.1f}-{max(devs):.1f}] | "
            f"{common.median([r.backlog_end for r in rs]):.0f} "
            f"({common.median([statistics.fmean(r.fair.values()) for r in rs]):.0f} s) | "
            f"{common.median([r.makespan for r in rs]):.0f} "
            f"({common.median([x['makespan_lower_bound_s'] for x in mine]):.0f}) |")
    out.append("")
    for workers, rs in runs.items():
        got = [burst(r) for r in rs]
        out.append(f"- {workers} workers: at time 0 (every worker asks before any action is "
                   f"done) the first actions went to {', '.join(str(u) for u, _ in got)} "
                   f"users (one user got up to {max(m for _, m in got)} workers), per seed")
    return out
