"""Worker restart: what a renderer process killed in the middle of a job costs that job.

A job (the Cornell box's walls, 64x64, 4 spp) runs; once it has passed its first checkpoint
(the daemon writes one after 10 iterations), its worker process (pid from GetServerInfo) gets
SIGKILL, as a crash inside Mitsuba or the kernel's out-of-memory killer would deliver it. The
daemon starts a fresh worker and the job goes on from its checkpoint. Reported over several
kills, one per job (a job whose worker dies twice is failed on purpose, so each kill gets a
job of its own): the time from the kill to the job's next iteration as its WatchJob stream
delivers it (median and spread), with the fresh worker's own start (import Mitsuba, set the
variant, a warm-up render; from the daemon's log) and the iterations that ran again (those
after the checkpoint). Checked for every job: it succeeds, says why it was resumed, and its
history has each iteration exactly once, in order, with its optimizing clock never going
back: no gap and no duplicate from the replay.
"""

from __future__ import annotations

import os
import re
import signal
import threading
import time

import common
from common import Result, Settings, Target
from matopt_client import client as mc
from matopt_api.v1 import matopt_pb2 as pb

RES, SPP = 64, 4
ITERATIONS = 40
KILL_AT = 15  # iterations done before the kill: past the first checkpoint (10)


def follow(client: mc.Client, name: str, killed: threading.Event, out: dict) -> None:
    """The job's stream: when the first iteration of the reloaded job arrived, and the end.
    The reload is the job event that says where the job was resumed from: an iteration
    event of before the kill still on its way cannot pass for the next one."""
    reloaded = False
    for event in mc.watch(client, name):
        if event.HasField("job"):
            reloaded = reloaded or (killed.is_set() and event.job.resumed_from not in
                                    ("", "pending"))
            if event.job.state in mc.TERMINAL_STATES:
                out["job"] = event.job
        elif reloaded and "next" not in out:
            out["next"] = time.perf_counter()
            out["next_iteration"] = event.iteration.iteration


def wait_iteration(client: mc.Client, name: str, at_least: int, timeout: float = 300) -> pb.Job:
    deadline = time.monotonic() + timeout
    while True:
        job = client.jobs.GetJob(pb.GetJobRequest(name=name))
        if job.iteration >= at_least or job.state in mc.TERMINAL_STATES:
            return job
        if time.monotonic() > deadline:
            raise RuntimeError(f"{name} did not reach iteration {at_least} in {timeout:g} s")
        time.sleep(0.02)


def worker_start_seconds(log: str) -> list[float]:
    """Each worker start the daemon logged ("workers/0 ready in 2.3 s: ...")."""
    return [float(s) for s in re.findall(r"workers/\d+ ready in ([0-9.]+) s", log)]


def history_problems(history: list[pb.IterationRecord], iterations: int) -> list[str]:
    """What is wrong with a finished job's history: missing, repeated or reordered
    iterations, or an optimizing clock that goes back."""
    problems = []
    numbers = [r.iteration for r in history]
    if numbers != list(range(iterations)):
        missing = sorted(set(range(iterations)) - set(numbers))
        repeated = sorted({n for n in numbers if numbers.count(n) > 1})
        problems.append(f"iterations missing {missing[:5]}, repeated {repeated[:5]}")
    seconds = [r.seconds for r in history]
    back = [i for i in range(1, len(seconds)) if seconds[i] < seconds[i - 1]]
    if back:
        problems.append(f"the clock goes back at iteration(s) {back[:5]}")
    return problems


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    kills = 2 if settings.quick else 5
    client = server.client
    scene = common.cornell(client, RES)
    ref_blob, _ = common.reference(client, scene, 32, settings.work)
    spec = common.wall_spec(scene, ref_blob, iterations=ITERATIONS, spp=SPP)
    common.require_success(common.run_job(client, spec), "worker_restart warm-up")
    rows, recoveries, replayed, broken = [], [], [], []
    for k in range(kills):
        name = client.jobs.CreateJob(pb.CreateJobRequest(spec=spec)).name
        killed, seen = threading.Event(), {}
        watcher = threading.Thread(target=follow, args=(client, name, killed, seen),
                                   daemon=True)
        watcher.start()
        at = wait_iteration(client, name, KILL_AT).iteration
        pid = server.worker_pids()[0]
        t_kill = time.perf_counter()
        killed.set()
        os.kill(pid, signal.SIGKILL)
        watcher.join(300)
        job = seen.get("job") or client.jobs.GetJob(pb.GetJobRequest(name=name))
        history = list(client.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=name)).iterations)
        problems = history_problems(history, ITERATIONS)
        if job.state != pb.JOB_STATE_SUCCEEDED:
            problems.insert(0, f"ended {mc.state_name(job.state)}: {job.error}")
        if not any("SIGKILL" in n for n in job.notes):
            problems.append("no note says why the job was resumed")
        recovery = seen["next"] - t_kill if "next" in seen else float("nan")
        again = at - seen.get("next_iteration", at)
        if "next" in seen:
            recoveries.append(recovery)
            replayed.append(again)
        broken += [f"kill {k + 1}: {p}" for p in problems]
        rows.append({"kill": k + 1, "iteration_at_kill": at, "kill_to_next_iteration_s": recovery,
                     "resumed_from": job.resumed_from, "iterations_run_again": again,
                     "state": mc.state_name(job.state), "history_ok": not problems})
    starts = worker_start_seconds(server.log.read_text())
    csv = common.write_csv(settings.out / "worker_restart.csv", rows)
    return Result("worker_restart", "A worker killed during a job", [
        Target("kill -9 of the worker to the job's next iteration",
               f"{common.spread(recoveries, '{:.2f}')} s", None),
        Target("jobs that then finished with every iteration once, in order",
               f"{kills - len({b.split(':')[0] for b in broken})} of {kills}"
               + (f" ({'; '.join(broken)})" if broken else ""), not broken),
    ], [
        f"Job: Cornell box walls, {RES}x{RES}, {SPP} spp, {ITERATIONS} iterations; killed "
        f"after iteration {KILL_AT}; {kills} kills, one per job.",
        f"- a worker's start (import Mitsuba, set the variant, warm-up render), as the daemon "
        f"logged it: first {starts[0]:.1f} s, restarts "
        f"{common.spread(starts[1:], '{:.1f}')} s" if starts else "- no worker start logged",
        f"- iterations run again after the restart (done after the checkpoint): "
        f"{common.spread(replayed, '{:.0f}')}",
        "- the job is resumed from its checkpoint on the fresh worker (resumed_from: "
        f"{rows[-1]['resumed_from'] if rows else '?'})",
    ], [csv], time.perf_counter() - began)
