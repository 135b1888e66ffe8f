"""Switching: many users' jobs time-sliced on one worker, against one job alone.

8 users with 5 jobs each (40 jobs: the Cornell box's walls from grey, 32x32, 4 spp, constant
rate, far more iterations than the case runs, so none ends) share the daemon's worker(s).
The scheduler gives a job its worker for a slice (scheduler.SLICE_SECONDS) while others wait,
picks the next by fair share per user, and switches by checkpointing and releasing one job
and loading the next: one job resident per worker, so every slice pays one switch. Rounds
alternate between a window with all 40 jobs running (the alone job paused) and one of the
same length with a single such job of another user alone (the 40 paused); each window starts
once the worker has switched at least once and counts iterations from ListJobs at both ends,
and the worker processes' CPU time.

Reported:
- throughput: iterations per second of all 40 jobs together / of the job alone, per worker
  (target >= 0.80). What is missing is what switches cost. Also the workers' CPU per
  iteration, together / alone: the same question in work done, which other tenants of a
  shared machine disturb far less than time;
- the switch itself, from every job's WatchJob stream and history: a step call's iterations
  arrive together, right after the call, so the time from a job's last arrival to the next
  job's first, less that first call's iterations at the pace the job kept for the rest of
  its slice (its clock, from its history), is what the switch took: checkpoint and release
  of one job, load of the next, slower first iterations after a load, and the calls'
  bookkeeping. Also each slice as run, from its first iteration's start to its last
  arrival, against the scheduler's slice length;
- the wait of a new user: while the 40 jobs run, a user with nothing queued creates a job;
  the time from CreateJob sent to its first iteration's WatchJob event, over several new
  users arriving at different points of a slice (target: max <= 5 s; fair share puts a
  newcomer next, so the wait is the rest of the running slice plus one switch and one
  iteration). Each new user's job is cancelled after its first iteration.
On a GPU the same runs on the daemon's CUDA worker(s).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import common
from common import Result, Settings, Target
from matopt_client import client as mc
from matopt_api.v1 import matopt_pb2 as pb
from matoptd.scheduling.scheduler import SLICE_SECONDS

RES, SPP = 32, 4
USERS, JOBS_PER_USER = 8, 5
NEWCOMERS = 8               # users who arrive while the 40 jobs run (fewer in --quick)
ENDLESS = 100_000           # iterations: no job ends within the case
TARGET_THROUGHPUT = 0.80    # together / alone
TARGET_WAIT = 5.0           # seconds, the longest wait of a new user
BURST = 0.005               # seconds: events of one step call arrive closer than this
TENANTS = [f"user{i}" for i in range(USERS)]
ALONE = "solo"
NEW = [f"newcomer{i}" for i in range(NEWCOMERS)]
DAEMON = {"users": [ALONE, *TENANTS, *NEW]}  # run.py starts the case's daemon with these


def prepare(server: common.Daemon, user: str, settings: Settings) -> tuple[mc.Client, pb.JobSpec]:
    """The user's client and job spec: their own Cornell box and reference."""
    client = server.connect(user)
    scene = common.cornell(client, RES)
    ref_blob, _ = common.reference(client, scene, 32, settings.work)
    return client, common.wall_spec(scene, ref_blob, iterations=ENDLESS, spp=SPP)


def create(client: mc.Client, spec: pb.JobSpec) -> str:
    return client.jobs.CreateJob(pb.CreateJobRequest(spec=spec)).name


def jobs_of(clients: dict[str, mc.Client]) -> dict[str, pb.Job]:
    """Every job of these users, by name (ListJobs shows a user only their own)."""
    out = {}
    for client in clients.values():
        for job in mc.list_all(client.jobs.ListJobs, pb.ListJobsRequest(page_size=1000),
                               "jobs"):
            out[job.name] = job
    return out


def wait_states(clients: dict[str, mc.Client], names: dict[str, str], states,
                timeout: float = 120) -> None:
    """Until every job (name -> user) is in one of ``states``."""
    deadline = time.monotonic() + timeout
    while True:
        jobs = jobs_of({u: clients[u] for u in set(names.values())})
        if all(jobs[n].state in states for n in names):
            return
        if time.monotonic() > deadline:
            late = {n: pb.JobState.Name(jobs[n].state) for n in names
                    if jobs[n].state not in states}
            raise RuntimeError(f"jobs did not reach {states} in {timeout:g} s: {late}")
        time.sleep(0.1)


def first_iteration(client: mc.Client, name: str, since: float) -> float:
    """When the job's next iteration arrived (perf_counter - ``since``)."""
    start: int | None = None
    for event in mc.watch(client, name):
        if event.HasField("job") and start is None:
            start = event.job.iteration  # the stream opens with the job as it is
        elif event.HasField("iteration") and event.iteration.iteration >= (start or 0):
            return time.perf_counter() - since
        if event.HasField("job") and event.job.state in mc.TERMINAL_STATES:
            break
    raise RuntimeError(f"job {name} ended before its next iteration")


def follow(client: mc.Client, name: str, out: list) -> None:
    """Appends (arrival, job, iteration) for each iteration event until the stream ends."""
    try:
        for event in mc.watch(client, name):
            if event.HasField("iteration"):
                out.append((time.perf_counter(), name, event.iteration.iteration))
    except Exception:  # noqa: BLE001 - the stream ends when the client closes
        pass


def window(server: common.Daemon, clients: dict[str, mc.Client], names: dict[str, str],
           seconds: float) -> dict:
    """Iterations and the workers' CPU seconds over ``seconds`` of the jobs' running, from
    ListJobs at both ends (each end timed at the middle of its calls)."""
    def snapshot() -> tuple[float, dict[str, pb.Job], float]:
        t0 = time.perf_counter()
        jobs = jobs_of({u: clients[u] for u in set(names.values())})
        return (t0 + time.perf_counter()) / 2, {n: jobs[n] for n in names}, server.cpu().workers

    t0, before, cpu0 = snapshot()
    time.sleep(seconds)
    t1, after, cpu1 = snapshot()
    return {"began": t0, "seconds": t1 - t0, "worker_cpu_seconds": cpu1 - cpu0,
            "iterations": sum(after[n].iteration - before[n].iteration for n in names)}


@dataclass
class Call:
    """One step call of a job as its events arrived: iterations first..last."""

    job: str
    first: int
    last: int
    arrived: float


def step_calls(events: list[tuple[float, str, int]]) -> list[Call]:
    """The arrivals grouped into step calls: a call's events come together."""
    calls: list[Call] = []
    for t, job, it in sorted(events):
        c = calls[-1] if calls else None
        if c is not None and c.job == job and it == c.last + 1 and t - c.arrived < BURST:
            c.last, c.arrived = it, t
        else:
            calls.append(Call(job, it, it, t))
    return calls


def switches(calls: list[Call], clock: dict[str, dict[int, float]]) -> tuple[list, list]:
    """Each switch's time and each whole slice as run. A switch runs from one job's last
    arrival to the next one's first, less the iterations of that first call at the pace the
    job then kept (its clock, from its history, over the slice's later iterations): what
    remains is checkpoint, release and load, and any slowness of the first iterations after
    a load. A slice runs from its first call's start to its last arrival. ``clock``: job ->
    iteration -> seconds."""
    slices: list[list[Call]] = []
    for c in calls:
        if slices and slices[-1][-1].job == c.job:
            slices[-1].append(c)
        else:
            slices.append([c])
    cost, length = [], []
    for before, after in zip(slices, slices[1:]):
        first, seconds = after[0], clock.get(after[0].job, {})
        steps = [seconds[i] - seconds[i - 1] for i in range(first.first + 2, after[-1].last + 1)
                 if i in seconds and i - 1 in seconds]
        if not steps:
            continue  # too short a slice to tell its pace
        own = (first.last - first.first + 1) * common.median(steps)
        cost.append(first.arrived - before[-1].arrived - own)
        length.append(after[-1].arrived - first.arrived + own)
    return cost, length[:-1]  # the window's end may cut its last slice short


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    rounds, measured, newcomers = (2, 8.0, 3) if settings.quick else (4, 20.0, NEWCOMERS)
    clients: dict[str, mc.Client] = {}
    specs: dict[str, pb.JobSpec] = {}
    for user in [ALONE, *TENANTS, *NEW[:newcomers]]:
        clients[user], specs[user] = prepare(server, user, settings)
    try:
        return measure(settings, server, clients, specs, rounds, measured, newcomers, began)
    finally:
        for client in clients.values():
            client.close()


def measure(settings: Settings, server: common.Daemon, clients: dict[str, mc.Client],
            specs: dict[str, pb.JobSpec], rounds: int, measured: float, newcomers: int,
            began: float) -> Result:
    workers = len(server.client.info.workers) or 1
    solo = {create(clients[ALONE], specs[ALONE]): ALONE}
    first_iteration(clients[ALONE], next(iter(solo)), time.perf_counter())  # warm: compiled
    many = {}
    for user in TENANTS:
        for _ in range(JOBS_PER_USER):
            many[create(clients[user], specs[user])] = user
    events: list[tuple[float, str, int]] = []
    for name, user in {**solo, **many}.items():  # the alone job too: the same streams' cost
        threading.Thread(target=follow, args=(clients[user], name, events), daemon=True).start()
    rows: list[dict] = []
    figures: dict[str, list[dict]] = {"alone": [], "together": []}

    def pause(names: dict[str, str]) -> None:
        for name, user in names.items():
            clients[user].jobs.PauseJob(pb.PauseJobRequest(name=name))
        wait_states(clients, names, (pb.JOB_STATE_PAUSED,))

    def resume(names: dict[str, str]) -> None:
        for name, user in names.items():
            clients[user].jobs.ResumeJob(pb.ResumeJobRequest(name=name))

    def alone(r: int) -> None:
        resume(solo)
        first_iteration(clients[ALONE], next(iter(solo)), time.perf_counter())  # stepping
        w = window(server, clients, solo, measured)
        pause(solo)
        figures["alone"].append(w)
        rows.append({"round": r, "jobs": 1, **w, "iterations_per_second":
                     w["iterations"] / w["seconds"]})

    def together(r: int) -> None:
        resume(many)
        time.sleep(SLICE_SECONDS + 1.0)  # past the first slice: switching from here on
        w = window(server, clients, many, measured)
        pause(many)
        figures["together"].append(w)
        rows.append({"round": r, "jobs": len(many), **w, "iterations_per_second":
                     w["iterations"] / w["seconds"]})

    pause(solo)
    pause(many)  # created running: all wait for the first round
    common.alternate(rounds, alone, together)
    clock = {name: {r.iteration: r.seconds for r in clients[user].jobs.GetJobHistory(
        pb.GetJobHistoryRequest(name=name)).iterations} for name, user in many.items()}
    cost, lengths = [], []
    for w in figures["together"]:
        c, s = switches(step_calls([e for e in events
                                    if w["began"] <= e[0] <= w["began"] + w["seconds"]]), clock)
        cost += c
        lengths += s

    # New users arriving while the 40 jobs run, at different points of a slice.
    resume(many)
    time.sleep(SLICE_SECONDS + 1.0)
    waits: list[float] = []
    for k, user in enumerate(NEW[:newcomers]):
        time.sleep((0.37 * k % 1.0) * SLICE_SECONDS)
        t0 = time.perf_counter()
        name = create(clients[user], specs[user])
        waits.append(first_iteration(clients[user], name, t0))
        rows.append({"round": "newcomer", "jobs": len(many) + 1, "user": user,
                     "create_to_first_iteration_s": waits[-1]})
        clients[user].jobs.CancelJob(pb.CancelJobRequest(name=name))
        wait_states(clients, {name: user}, (pb.JOB_STATE_CANCELLED,))
    pause(many)
    rows += [{"round": "switch", "switch_seconds": c} for c in cost]
    rows += [{"round": "slice", "slice_seconds": s} for s in lengths]

    alone_rate = [w["iterations"] / w["seconds"] for w in figures["alone"]]
    together_rate = [w["iterations"] / w["seconds"] for w in figures["together"]]
    # One job keeps one worker busy; together, every worker is: per worker, so that the
    # target means the same with several.
    ratios = [t / (a * workers) for a, t in zip(alone_rate, together_rate)]
    ratio = common.median(ratios)
    cpu_ratios = [(t["worker_cpu_seconds"] / t["iterations"])
                  / (a["worker_cpu_seconds"] / a["iterations"])
                  for a, t in zip(figures["alone"], figures["together"])]
    pace = common.median([w["seconds"] / w["iterations"] for w in figures["alone"]])
    csv = common.write_csv(settings.out / "switching.csv", rows)
    wait_max = max(waits) if waits else float("nan")
    switch, slice_ = common.median(cost), common.median(lengths)
    return Result("switching", "Many users' jobs time-sliced", [
        Target(f"iterations per second per worker, {len(many)} jobs of {USERS} users "
               "together / one job alone", f"{ratio:.3f} (target >= {TARGET_THROUGHPUT})",
               ratio >= TARGET_THROUGHPUT),
        Target(f"new user's CreateJob to first iteration while the {len(many)} jobs run",
               f"p50 {common.median(waits):.2f} s, max {wait_max:.2f} s (n={len(waits)}; "
               f"target max <= {TARGET_WAIT:g} s)", wait_max <= TARGET_WAIT),
        Target("workers' CPU per iteration, together / alone (context: work done)",
               f"{common.median(cpu_ratios):.3f}", None),
        Target("switch (checkpoint, release, load) against the slice",
               f"{switch * 1000:.0f} ms per slice of {slice_:.2f} s as run (scheduler slice "
               f"{SLICE_SECONDS:g} s): {switch / (switch + slice_):.1%} of the worker's time",
               None),
    ], [
        f"Jobs: Cornell box walls, {RES}x{RES}, {SPP} spp, constant rate; {USERS} users x "
        f"{JOBS_PER_USER} jobs on {workers} worker(s); {rounds} alternating rounds of "
        f"{measured:g} s windows, together and alone.",
        f"- alone: {common.spread(alone_rate, '{:.1f}')} iterations/s "
        f"({pace * 1000:.1f} ms per iteration)",
        f"- together: {common.spread(together_rate, '{:.1f}')} iterations/s; ratio per "
        f"round: {', '.join(f'{x:.3f}' for x in ratios)}; workers' CPU per iteration, ratio "
        f"per round: {', '.join(f'{x:.3f}' for x in cpu_ratios)}",
        f"- switches: {common.spread([c * 1000 for c in cost], '{:.0f}')} ms, p90 "
        f"{common.percentile(cost, 90) * 1000:.0f} ms; slices as run: "
        f"{common.spread(lengths, '{:.2f}')} s (the scheduler's slice is {SLICE_SECONDS:g} s; "
        "a slice ends at the first step call to end past it)",
        f"- new users' waits: {', '.join(f'{w:.2f} s' for w in waits)}",
    ], [csv], time.perf_counter() - began)
