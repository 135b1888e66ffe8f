"""Two workers: two jobs at once in two renderer processes, against the same two jobs taking
turns in one.

On the CPU: ``matoptd --workers 2`` (two worker processes, one core each) against ``matoptd
--workers 1`` (one process rendering with every core). On a GPU: two workers sharing one
device (``--devices 0,0``, two CUDA contexts) against one (``--devices 0``). Each round starts
the same two jobs (the Cornell box's walls, 64x64, 4 spp, constant rate) at once on one
daemon, then on the other (alternating which goes first), and times them from the first
CreateJob to the last one's end: total iterations per second, two workers / one. With one
worker the jobs take turns in slices (each switch checkpoints one job and loads the other);
with two each has a process, and they share the cores (or the GPU) instead. A warm-up pair on
each daemon compiles the kernels first (every worker compiles its own, or loads them from
the daemon's kernel cache on disk). No target: this says which configuration to run.
"""

from __future__ import annotations

import time

import common
from common import Result, Settings, Target
from matopt_api.v1 import matopt_pb2 as pb

RES, SPP = 64, 4


def pair(server: common.Daemon, spec, what: str) -> dict:
    """Both jobs started at once; the figures of the pair."""
    done = common.run_together(server, [(server.client, spec)] * 2, f"two_workers {what}")
    n = done.iterations
    return {"workers": what, "seconds": done.seconds, "iterations": n,
            "iterations_per_second": n / done.seconds,
            "job_seconds_per_iteration": common.median([common.per_iteration(r.seconds)
                                                         for r in done.runs]),
            "worker_cpu_seconds_per_iteration": done.cpu.workers / n,
            "server_cpu_seconds_per_iteration": done.cpu.server / n}


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    iterations, rounds = (20, 2) if settings.quick else (100, 4)
    if server.cuda:
        sides = {"one": ["--devices", "0"], "two": ["--devices", "0,0"]}
        place = "one CUDA device"
    else:
        sides = {"one": ["--workers", "1"], "two": ["--workers", "2"]}
        place = "the CPU's cores"
    rows: list[dict] = []
    figures: dict[str, list[dict]] = {"one": [], "two": []}
    with common.daemon(settings.work, "one-worker", sides["one"]) as one, \
            common.daemon(settings.work, "two-workers", sides["two"]) as two:
        daemons = {"one": one, "two": two}
        specs = {}
        for side, d in daemons.items():
            scene = common.cornell(d.client, RES)
            ref_blob, _ = common.reference(d.client, scene, 64, settings.work)
            specs[side] = common.wall_spec(scene, ref_blob, iterations=iterations, spp=SPP)
            pair(d, specs[side], side)  # warm-up: kernels compiled in every worker
        devices = {side: [w.device for w in d.client.server.GetServerInfo(
            pb.GetServerInfoRequest()).workers] for side, d in daemons.items()}

        def measure(side: str, r: int) -> None:
            row = pair(daemons[side], specs[side], side)
            figures[side].append(row)
            rows.append({"round": r, **row})

        common.alternate(rounds, lambda r: measure("one", r), lambda r: measure("two", r))
    ratios = [b["iterations_per_second"] / a["iterations_per_second"]
              for a, b in zip(figures["one"], figures["two"])]
    ratio = common.median(ratios)
    csv = common.write_csv(settings.out / "two_workers.csv", rows)

    def per(side: str, key: str, scale: float = 1000, fmt: str = "{:.0f}") -> str:
        return common.spread([f[key] * scale for f in figures[side]], fmt)

    return Result("two_workers", "Two workers against one", [
        Target(f"iterations per second of two jobs at once, two workers / one worker on "
               f"{place} (no target)", f"{ratio:.3f}", None),
    ], [
        f"Jobs: 2 x Cornell box walls, {RES}x{RES}, {SPP} spp, {iterations} iterations each, "
        f"started together; {rounds} alternating rounds after a warm-up pair on each daemon.",
        f"- one worker ({'; '.join(devices['one'])}): "
        f"{per('one', 'iterations_per_second', 1, '{:.1f}')} iterations/s; each job "
        f"{per('one', 'job_seconds_per_iteration')} ms per iteration while it ran",
        f"- two workers ({'; '.join(devices['two'])}): "
        f"{per('two', 'iterations_per_second', 1, '{:.1f}')} iterations/s; each job "
        f"{per('two', 'job_seconds_per_iteration')} ms per iteration",
        f"- ratio per round: {', '.join(f'{x:.3f}' for x in ratios)}",
        f"- workers' CPU per iteration: one worker {per('one', 'worker_cpu_seconds_per_iteration')}"
        f" ms, two workers {per('two', 'worker_cpu_seconds_per_iteration')} ms; the server's "
        f"{per('one', 'server_cpu_seconds_per_iteration', 1000, '{:.1f}')} ms and "
        f"{per('two', 'server_cpu_seconds_per_iteration', 1000, '{:.1f}')} ms",
    ], [csv], time.perf_counter() - began)
