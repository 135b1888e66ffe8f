"""Control plane: status traffic while a job runs, and what it costs the job.

While the overhead case's job runs (Cornell box walls, 128x128, 4 spp), a bounded set of
clients on loopback, each with its own channel, polls GetJob at 200 requests per second in
all (evenly paced, never bursting to catch up) and holds WatchJob streams on the job. Rounds
alternate with the same job alone. Reported: GetJob latency percentiles (also with the daemon
idle, for reference), the rate reached, the job's slowdown per iteration against the job
alone, and the CPU per iteration of the daemon's server process (which serves the load) and
of its worker (which renders) separately, and one user's GetJob latency at 2 calls a second
during a job with no other load (what a person polling the job sees). For reference, the
same pollers against a ``grpc.aio`` server whose GetJob returns a prebuilt message: gRPC's own
CPU per call, the floor under any handler.

Two layouts, each with its own alternating rounds:
- shared: the daemon as it starts by default (its server threads at the lowest priority,
  nice 19, below the worker: matoptd.main.server_nice). Its server process (gRPC) and the load
  generator (this process) run on the same cores as the worker's render threads, so on a
  machine whose cores all render (the LLVM backend uses every core it is given) the CPU the
  load takes comes out of the job's share: this figure says what status traffic costs a
  CPU-only machine that renders on every core;
- pinned: ``matoptd --server-cores 1``: the server process on the first core, the worker on
  the others, and the load generator pinned to the server's core. The worker renders with one
  core fewer (so both its alone and loaded times are longer than shared), but nothing else
  runs on its cores: this figure says whether the control plane disturbs rendering when it
  has a core of its own, as it has where the renderer is a GPU. Needs at least 2 cores.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from contextlib import contextmanager
import time
from dataclasses import dataclass, field

import common
from common import Result, Settings, Target
from matopt_client import client as mc
from matopt_api.v1 import matopt_pb2 as pb

RES, SPP = 128, 4
RATE = 200.0      # GetJob requests per second, all pollers together
POLLERS = 8
WATCHERS = 16
LIGHT_RATE = 2.0  # one user's GetJob per second, as `matopt job status` in a loop asks
TARGET = 0.05     # slowdown per iteration
MAX_SECONDS = 120  # no load runs longer than this, whatever happens to the job


@dataclass
class Load:
    """A running load: pollers and watchers on their own channels until ``stop``."""

    address: str
    job: str
    rate_asked: float = RATE    # GetJob requests per second, all pollers together
    pollers: int = POLLERS
    stop: threading.Event = field(default_factory=threading.Event)
    latencies: list[float] = field(default_factory=list)
    errors: int = 0
    events: int = 0
    threads: list[threading.Thread] = field(default_factory=list)
    began: float = 0.0
    ended: float = 0.0
    cpu: float = 0.0

    def start(self, watchers: int = WATCHERS) -> "Load":
        self.began, self.cpu = time.perf_counter(), time.process_time()
        for n in range(self.pollers):
            self.threads.append(threading.Thread(target=self._poll, args=(n,), daemon=True))
        for _ in range(watchers):
            self.threads.append(threading.Thread(target=self._watch, daemon=True))
        for t in self.threads:
            t.start()
        return self

    def finish(self) -> "Load":
        self.stop.set()
        for t in self.threads:
            t.join(10)
        self.ended = time.perf_counter()
        self.cpu = time.process_time() - self.cpu
        return self

    @property
    def rate(self) -> float:
        return len(self.latencies) / (self.ended - self.began)

    def _poll(self, n: int) -> None:
        period = self.pollers / self.rate_asked
        client = mc.connect(self.address, probe_timeout=None)
        request = pb.GetJobRequest(name=self.job)
        due = time.perf_counter() + period * n / self.pollers  # staggered
        deadline = time.perf_counter() + MAX_SECONDS
        try:
            while not self.stop.is_set() and time.perf_counter() < deadline:
                wait = due - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
                t0 = time.perf_counter()
                try:
                    client.jobs.GetJob(request, timeout=10)
                    self.latencies.append(time.perf_counter() - t0)
                except Exception:  # noqa: BLE001 - counted, not fatal
                    self.errors += 1
                due = max(due + period, time.perf_counter())  # late: no burst to catch up
        finally:
            client.close()

    def _watch(self) -> None:
        client = mc.connect(self.address, probe_timeout=None)
        stream = client.jobs.WatchJob(pb.WatchJobRequest(name=self.job), timeout=MAX_SECONDS)
        try:
            for _ in stream:
                self.events += 1
                if self.stop.is_set():
                    break
        except Exception:  # noqa: BLE001 - cancelled at the end, or the job ended
            pass
        finally:
            stream.cancel()
            client.close()


# gRPC's own floor: a grpc.aio server whose GetJob returns one prebuilt message, nothing else.
CONSTANT_SERVER = """
import asyncio, sys, grpc
from matopt_api.v1 import matopt_pb2 as pb, matopt_pb2_grpc as rpc
JOB = pb.Job(name="jobs/constant", iteration=50, notes=["a note"] * 4)
class Jobs(rpc.JobServiceServicer):
    async def GetJob(self, request, context):
        return JOB
async def main():
    server = grpc.aio.server()
    rpc.add_JobServiceServicer_to_server(Jobs(), server)
    print(server.add_insecure_port("127.0.0.1:0"), flush=True)
    await server.start()
    await server.wait_for_termination()
asyncio.run(main())
"""


def grpc_floor(seconds: float) -> tuple[float, float]:
    """Server CPU seconds per GetJob, and the rate reached, of ``CONSTANT_SERVER`` under the
    pollers alone: what any Python gRPC server spends per call here, before a handler."""
    process = subprocess.Popen([sys.executable, "-c", CONSTANT_SERVER], stdout=subprocess.PIPE,
                               text=True)
    try:
        port = int(process.stdout.readline())
        before = common.cpu_seconds(process.pid)
        load = Load(f"127.0.0.1:{port}", "jobs/constant").start(watchers=0)
        time.sleep(seconds)
        load.finish()
        return ((common.cpu_seconds(process.pid) - before) / max(len(load.latencies), 1),
                load.rate)
    finally:
        process.kill()
        process.wait()


def percentiles_ms(latencies: list[float]) -> str:
    return ", ".join(f"p{p} {common.percentile(latencies, p) * 1000:.1f} ms" for p in (50, 95, 99))


@contextmanager
def pinned_to(cores: set[int]):
    """Every thread of this process (gRPC's own included) on ``cores`` for the block; the
    threads started inside inherit it."""
    tasks = [int(t) for t in os.listdir("/proc/self/task")]
    before = {t: os.sched_getaffinity(t) for t in tasks}
    for t in tasks:
        os.sched_setaffinity(t, cores)
    try:
        yield
    finally:
        for t, mask in before.items():
            try:
                os.sched_setaffinity(t, mask)
            except OSError:  # that thread ended
                pass
        for t in os.listdir("/proc/self/task"):  # threads started inside: back to all
            if int(t) not in before:
                try:
                    os.sched_setaffinity(int(t), before[os.getpid()])
                except OSError:
                    pass


@dataclass
class Layout:
    """One layout's rounds: per-iteration times and CPU, loads, the idle reference."""

    name: str
    alone: list[float] = field(default_factory=list)   # the job's clock, per iteration
    loaded: list[float] = field(default_factory=list)
    wall: dict[str, list[float]] = field(default_factory=lambda: {"alone": [], "loaded": []})
    cpu: dict[str, list[common.Cpu]] = field(default_factory=lambda: {"alone": [],
                                                                       "loaded": []})
    loads: list[Load] = field(default_factory=list)
    idle: Load | None = None
    light: Load | None = None  # one user's polls during a job, nothing else
    per_request: float = 0.0  # server CPU seconds per GetJob, idle
    rows: list[dict] = field(default_factory=list)

    @property
    def slowdowns(self) -> list[float]:
        return [b / a - 1 for a, b in zip(self.alone, self.loaded)]

    @property
    def latencies(self) -> list[float]:
        return [x for load in self.loads for x in load.latencies]

    @property
    def server_share(self) -> float:
        """The server process's CPU under load, in cores."""
        shares = [c.server / w for c, w in zip(self.cpu["loaded"], self.wall["loaded"])]
        return common.median([x for x in shares if x == x])  # a nan: see lines()

    def cpu_ratio(self, process: str) -> float:
        ratios = [getattr(b, process) / getattr(a, process)
                  for a, b in zip(self.cpu["alone"], self.cpu["loaded"])]
        return common.median([r for r in ratios if r == r])  # a nan: see lines()


def per_iteration_cpu(run_: common.JobRun) -> common.Cpu:
    return common.Cpu(common.per_iteration(run_.cpu_server),
                      common.per_iteration(run_.cpu_workers))


def measure(layout: Layout, server: common.Daemon, settings: Settings, iterations: int,
            rounds: int) -> Layout:
    client = server.client
    scene = common.cornell(client, RES)
    ref_blob, _ = common.reference(client, scene, 64, settings.work)
    spec = common.wall_spec(scene, ref_blob, iterations=iterations, spp=SPP)
    warm = common.run_job(client, spec)  # warm-up: kernels compiled; its name serves idle polls
    common.require_success(warm, "control_plane warm-up")

    idle_cpu = server.cpu().server
    layout.idle = Load(server.address, warm.job.name).start(watchers=0)
    time.sleep(1.0 if settings.quick else 4.0)
    layout.idle.finish()
    layout.per_request = ((server.cpu().server - idle_cpu)
                          / max(len(layout.idle.latencies), 1))

    def without(r: int) -> None:
        run_ = common.run_job(client, spec, server=server)
        common.require_success(run_, "control_plane")
        layout.alone.append(common.per_iteration(run_.seconds))
        layout.wall["alone"].append(common.per_iteration(run_.arrivals))
        layout.cpu["alone"].append(per_iteration_cpu(run_))
        layout.rows.append({"layout": layout.name, "round": r, "load": "none",
                            "seconds_per_iteration": layout.alone[-1],
                            "wall_seconds_per_iteration": layout.wall["alone"][-1],
                            "server_cpu_seconds_per_iteration": layout.cpu["alone"][-1].server,
                            "worker_cpu_seconds_per_iteration": layout.cpu["alone"][-1].workers})

    def under_load(r: int) -> None:
        load: list[Load] = []
        run_ = common.run_job(client, spec, on_created=lambda name: load.append(
            Load(server.address, name).start()), server=server)
        load[0].finish()
        common.require_success(run_, "control_plane")
        layout.loaded.append(common.per_iteration(run_.seconds))
        layout.wall["loaded"].append(common.per_iteration(run_.arrivals))
        layout.cpu["loaded"].append(per_iteration_cpu(run_))
        layout.loads.append(load[0])
        layout.rows.append({
            "layout": layout.name, "round": r, "load": f"{RATE:g} GetJob/s + {WATCHERS} watchers",
            "seconds_per_iteration": layout.loaded[-1],
            "wall_seconds_per_iteration": layout.wall["loaded"][-1],
            "server_cpu_seconds_per_iteration": layout.cpu["loaded"][-1].server,
            "worker_cpu_seconds_per_iteration": layout.cpu["loaded"][-1].workers,
            "getjob_rate": load[0].rate, "getjob_errors": load[0].errors,
            "watch_events": load[0].events,
            "p50_ms": common.percentile(load[0].latencies, 50) * 1000,
            "p95_ms": common.percentile(load[0].latencies, 95) * 1000,
            "p99_ms": common.percentile(load[0].latencies, 99) * 1000,
            "client_cpu_share": load[0].cpu / (load[0].ended - load[0].began)})

    common.alternate(rounds, without, under_load)
    light: list[Load] = []
    run_ = common.run_job(client, spec, on_created=lambda name: light.append(
        Load(server.address, name, LIGHT_RATE, 1).start(watchers=0)), server=server)
    layout.light = light[0].finish()
    common.require_success(run_, "control_plane")
    return layout


def lines(layout: Layout, what: str) -> list[str]:
    loads = layout.loads
    rate = sum(len(x.latencies) for x in loads) / sum(x.ended - x.began for x in loads)
    client_cpu = sum(x.cpu for x in loads) / sum(x.ended - x.began for x in loads)
    # A round whose own watch saw fewer than two iterations (its events waited behind a
    # starved server) has no per-iteration figures as the client sees them: left out, "n/a".
    ms = lambda xs, fmt="{:.0f}": common.spread(  # noqa: E731
        [x * 1000 for x in xs if x == x], fmt)
    pct = lambda x: f"{x:+.1%}" if x == x else "n/a"  # noqa: E731
    busy = lambda x: f"{x:.2f}" if x == x else "n/a"  # noqa: E731
    return [
        f"**{layout.name}** ({what}):",
        f"- rate reached {rate:.0f} GetJob/s, {sum(x.errors for x in loads)} errors, "
        f"{sum(x.events for x in loads)} WatchJob events delivered",
        f"- GetJob latency during the job: {percentiles_ms(layout.latencies)}; daemon idle: "
        f"{percentiles_ms(layout.idle.latencies)} ({layout.idle.rate:.0f}/s); one user's "
        f"{LIGHT_RATE:g}/s alone during a job: {percentiles_ms(layout.light.latencies)}",
        f"- slowdown per round: {', '.join(f'{s:+.1%}' for s in layout.slowdowns)}; per "
        f"iteration alone {ms(layout.alone)} ms, loaded {ms(layout.loaded)} ms (the job's "
        "clock); as the client sees iterations arrive: slowdown "
        + ", ".join(pct(b / a - 1) for a, b in zip(layout.wall["alone"],
                                                   layout.wall["loaded"])),
        f"- worker CPU per iteration: alone {ms([c.workers for c in layout.cpu['alone']])} ms, "
        f"loaded {ms([c.workers for c in layout.cpu['loaded']])} ms; server CPU per "
        f"iteration: alone {ms([c.server for c in layout.cpu['alone']], '{:.1f}')} ms, loaded "
        f"{ms([c.server for c in layout.cpu['loaded']], '{:.1f}')} ms",
        "- the worker's CPU per second of the job (cores it kept busy): alone "
        + ", ".join(busy(c.workers / w) for c, w in zip(layout.cpu["alone"],
                                                         layout.wall["alone"]))
        + ", loaded " + ", ".join(busy(c.workers / w) for c, w in zip(
            layout.cpu["loaded"], layout.wall["loaded"]))
        + ": where it does the same work per iteration but keeps fewer cores busy, it waited "
        "for its cores",
        f"- the load generator itself used {client_cpu:.0%} of one core; the idle server "
        f"spends {layout.per_request * 1000:.2f} ms of CPU per GetJob (gRPC's Python server, "
        f"mostly), so {RATE:g}/s take {RATE * layout.per_request:.0%} of one core before any "
        "watch stream",
        "",
    ]


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    iterations, rounds = (10, 2) if settings.quick else (50, 4)
    floor, floor_rate = grpc_floor(1.0 if settings.quick else 4.0)
    shared = measure(Layout("shared"), server, settings, iterations, rounds)
    layouts = [shared]
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) >= 2:
        with common.daemon(settings.work, "control_plane-pinned", ["--server-cores", "1"]) \
                as pinned_server, pinned_to(os.sched_getaffinity(pinned_server.pid)):
            pinned = measure(Layout("pinned"), pinned_server, settings, iterations, rounds)
            pinned.name = (f"pinned: server and load on core(s) "
                           f"{sorted(os.sched_getaffinity(pinned_server.pid))}, worker on "
                           f"{pinned_server.client.info.workers[0].device}")
        layouts.append(pinned)
    targets = []
    for layout in layouts:
        slowdown = common.median(layout.slowdowns)
        short = layout.name.split(":")[0]
        targets += [
            Target(f"{short}: job slowdown per iteration at {RATE:g} GetJob/s + {WATCHERS} "
                   "WatchJob streams", f"{slowdown:+.1%} (target < {TARGET:.0%})",
                   slowdown < TARGET),
            Target(f"{short}: GetJob latency during the job", percentiles_ms(layout.latencies),
                   None),
            Target(f"{short}: one user's GetJob latency at {LIGHT_RATE:g}/s during the job, "
                   "no other load", percentiles_ms(layout.light.latencies), None),
            Target(f"{short}: worker CPU per iteration, loaded / alone; the server's CPU "
                   "under load (context: work done, which other tenants disturb far less "
                   "than time)", f"{layout.cpu_ratio('workers'):.3f}x; server "
                   f"{layout.server_share:.0%} of a core", None)]
    targets.append(Target(
        "server CPU per GetJob, idle daemon / a grpc.aio server returning a constant (gRPC's "
        "own floor)", f"{shared.per_request * 1000:.2f} ms / {floor * 1000:.2f} ms", None))
    csv = common.write_csv(settings.out / "control_plane.csv",
                           [row for layout in layouts for row in layout.rows])
    text = [f"Job: Cornell box walls, {RES}x{RES}, {SPP} spp, {iterations} iterations; {rounds} "
            f"alternating rounds per layout; {POLLERS} polling clients and {WATCHERS} watching "
            "clients, each on its own loopback channel.", ""]
    text += [f"gRPC's own floor: a `grpc.aio` server whose GetJob returns one prebuilt message "
             f"spends {floor * 1000:.2f} ms of CPU per call under the same pollers "
             f"({floor_rate:.0f}/s reached), so {RATE:g} calls a second cost "
             f"{RATE * floor:.0%} of one core in any Python gRPC server before its handler.",
             ""]
    text += lines(shared, "the default: server, worker and load generator on every core")
    if len(layouts) > 1:
        text += lines(layouts[1], "the control plane on a core of its own")
    else:
        text += ["The pinned layout needs at least 2 cores; this machine has 1."]
    text += ["Which figure answers what: *shared* is the cost of status traffic on a CPU-only "
             "machine whose every core renders (the load's CPU is taken from the job); "
             "*pinned* is whether the control plane disturbs rendering once it has a core of "
             "its own, as on a GPU machine or with `matoptd --server-cores`. On a GPU the "
             "job's work is on the device and both measure the server's own scheduling. On a "
             "machine shared with other people's processes, which no pinning here holds, "
             "those move to the worker's core while the server's is busy: the pinned "
             "figure then includes them, and the worker's busy cores above show it."]
    return Result("control_plane", "Control plane under load", targets, text, [csv],
                  time.perf_counter() - began)
