"""Overhead: what the daemon costs per iteration over a plain Mitsuba script doing the same job.

The job: the Cornell box's red and green walls from grey, 128x128, 4 spp, 50 iterations,
Adam 0.03, MSE, constant rate, against the same reference image. The daemon (started once)
runs it as a job in its renderer worker process; the script is bench/plain.py's tutorial loop
with the same integrator (prb, max_depth 8 from the scene). Rounds alternate; one warm-up
round of each compiles the kernels and is not counted. Per-iteration time is steady state,
iteration 0 (load, compilation) left out: from the daemon's history (the worker's optimizing
clock) and, as a user would see it, from when the client received each iteration's WatchJob
event (which adds the worker's step calls, the server's store writes and the events). CPU
per iteration is read per process: the worker's (the job's work, against the script's) and
the server's (gRPC, store, scheduler: what the daemon adds beside the renderer). Both sides
use the same render seeds (the daemon's seed 0 gives iteration i the seed i, as the script
does), so they do the same work and their losses agree, which the summary checks.
"""

from __future__ import annotations

import math
import time

import common
import plain
from common import Result, Settings, Target

RES, SPP, LR = 128, 4, 0.03
TARGET = 1.03  # daemon seconds per iteration / plain loop's


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    iterations, rounds = (15, 2) if settings.quick else (50, 4)
    client = server.client
    scene = common.cornell(client, RES)
    ref_blob, ref_path = common.reference(client, scene, 256, settings.work)
    baseline = plain.PlainSpec(common.CORNELL_XML, ref_path, {k: common.GREY for k in common.WALLS},
                               iterations, SPP, "prb", 8,
                               overrides={"resx": str(RES), "resy": str(RES)})
    rows: list[dict] = []
    daemon_iter: list[float] = []
    daemon_wall: list[float] = []
    plain_iter: list[float] = []
    worker_cpu: list[float] = []
    server_cpu: list[float] = []
    plain_cpu: list[float] = []
    last_job = None

    def through_plain(r: int) -> None:
        its = plain.run(baseline, server.variant)
        s = common.per_iteration([it.seconds for it in its])
        c = common.per_iteration([it.cpu for it in its])
        rows.append({"round": r, "method": "plain", "seconds_per_iteration": s,
                     "cpu_seconds_per_iteration": c,
                     "first_iteration_s": its[0].seconds, "loss0": its[0].loss,
                     "loss_last": its[-1].loss})
        if r >= 0:
            plain_iter.append(s)
            plain_cpu.append(c)

    def through_daemon(r: int) -> None:
        nonlocal last_job
        run_ = common.run_job(client, common.wall_spec(scene, ref_blob, iterations=iterations,
                                                       spp=SPP, seed=0), server=server)
        common.require_success(run_, "overhead")
        s, w = common.per_iteration(run_.seconds), common.per_iteration(run_.arrivals)
        c = common.per_iteration(run_.cpu_workers)
        c_server = common.per_iteration(run_.cpu_server)
        rows.append({"round": r, "method": "daemon", "seconds_per_iteration": s,
                     "cpu_seconds_per_iteration": c, "server_cpu_seconds_per_iteration": c_server,
                     "wall_seconds_per_iteration": w, "first_iteration_s": run_.seconds[0],
                     "loss0": run_.history[0].loss, "loss_last": run_.history[-1].loss})
        last_job = run_.job
        if r >= 0:
            daemon_iter.append(s)
            daemon_wall.append(w)
            worker_cpu.append(c)
            server_cpu.append(c_server)

    through_daemon(-1)  # warm-up: compiles kernels on both sides; not counted
    through_plain(-1)
    common.alternate(rounds, through_plain, through_daemon)

    same = [math.isclose(d["loss0"], p["loss0"], rel_tol=1e-4)
            and math.isclose(d["loss_last"], p["loss_last"], rel_tol=1e-4)
            for d, p in zip([x for x in rows if x["method"] == "daemon"],
                            [x for x in rows if x["method"] == "plain"])]
    ratios = [d / p for d, p in zip(daemon_iter, plain_iter)]
    wall_ratios = [d / p for d, p in zip(daemon_wall, plain_iter)]
    cpu_ratios = [d / p for d, p in zip(worker_cpu, plain_cpu)]
    ratio = common.median(ratios)
    csv = common.write_csv(settings.out / "overhead.csv", rows)
    return Result("overhead", "Daemon overhead per iteration", [
        Target("daemon time per iteration (history) / plain loop", f"{ratio:.3f} "
               f"(target <= {TARGET})", ratio <= TARGET),
        Target("daemon time per iteration as the client sees it / plain loop",
               f"{common.median(wall_ratios):.3f} (target <= {TARGET})",
               common.median(wall_ratios) <= TARGET),
        Target("worker CPU time per iteration / plain loop's",
               f"{common.median(cpu_ratios):.3f} (context: work done, less disturbed by "
               "other tenants; the server adds "
               f"{common.median(server_cpu) / common.median(plain_cpu):.1%})", None),
    ], [
        f"Cornell box walls from grey, {RES}x{RES}, {SPP} spp, {iterations} iterations, "
        f"Adam {LR} constant, MSE; {rounds} alternating rounds after one warm-up round each.",
        f"Integrator on both sides: {last_job.integrator if last_job else '?'} "
        f"({last_job.integrator_reason if last_job else ''}); the plain loop is given "
        "`mi.load_dict({'type': 'prb', 'max_depth': 8})` so the comparison is fair.",
        f"- plain loop: {common.spread([t * 1000 for t in plain_iter], '{:.1f}')} ms/iteration",
        f"- daemon (history): {common.spread([t * 1000 for t in daemon_iter], '{:.1f}')} "
        "ms/iteration",
        f"- daemon (WatchJob arrivals): {common.spread([t * 1000 for t in daemon_wall], '{:.1f}')}"
        " ms/iteration",
        f"- CPU per iteration: plain {common.spread([t * 1000 for t in plain_cpu], '{:.0f}')}"
        f" ms, the daemon's worker {common.spread([t * 1000 for t in worker_cpu], '{:.0f}')} "
        f"ms, its server process {common.spread([t * 1000 for t in server_cpu], '{:.1f}')} ms",
        f"- ratio per round (history): {', '.join(f'{x:.3f}' for x in ratios)}",
        f"- same losses on both sides (first and last iteration): {sum(same)} of {len(same)} "
        "rounds",
    ], [csv], time.perf_counter() - began)
