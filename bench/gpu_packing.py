"""GPU packing: many small jobs on one device, with as many workers as its memory holds
against one.

8 small jobs (the Cornell box's walls, 128x128, 4 spp, constant rate) of 4 users, started
together on one daemon, then on the other (alternating which goes first), timed from the first
CreateJob to the last one's end: total iterations per second, packed / one worker. On a GPU:
``matoptd --workers-per-device auto`` (the default: as many workers as the device's free memory
holds, workers/sizing.py) against ``--workers-per-device 1``; target >= 3x on an H100-class
GPU, where one small job leaves most of the device idle. On a CPU-only host ``auto`` is one
worker, so the packed side is ``--workers-per-device 2`` (two workers, each rendering on every
core): its cores are the limit, the ratio is expected near 1, and it says that packing costs
nothing there. A warm-up round on each daemon compiles every worker's kernels first.
"""

from __future__ import annotations

import time

import common
from common import Result, Settings, Target
from matopt_api.v1 import matopt_pb2 as pb

RES, SPP = 128, 4
USERS = [f"user{i}" for i in range(4)]
JOBS_PER_USER = 2
TARGET = 3.0  # on an H100-class GPU
NEEDS_DAEMON = False  # starts its own two daemons


def burst(server: common.Daemon, specs: dict[str, pb.JobSpec], what: str) -> dict:
    """Every user's jobs started at once; the figures of the round."""
    clients = {u: server.connect(u) for u in USERS}
    try:
        done = common.run_together(server, [(clients[u], specs[u]) for u in USERS
                                            for _ in range(JOBS_PER_USER)], f"gpu_packing {what}")
    finally:
        for c in clients.values():
            c.close()
    return {"side": what, "seconds": done.seconds, "iterations": done.iterations,
            "iterations_per_second": done.iterations / done.seconds,
            "worker_cpu_seconds_per_iteration": done.cpu.workers / done.iterations}


def run(settings: Settings, _: object = None) -> Result:
    began = time.perf_counter()
    iterations, rounds = (10, 2) if settings.quick else (40, 4)
    extra = ("--variant", settings.variant) if settings.variant else ()
    rows: list[dict] = []
    figures: dict[str, list[dict]] = {"one": [], "packed": []}
    with common.daemon(settings.work, "one-worker", (*extra, "--workers-per-device", "1"),
                       users=USERS) as one:
        packed_flag = "auto" if one.cuda else "2"
        with common.daemon(settings.work, "packed", (*extra, "--workers-per-device",
                                                     packed_flag), users=USERS) as packed:
            daemons = {"one": one, "packed": packed}
            specs: dict[str, dict[str, pb.JobSpec]] = {}
            for side, d in daemons.items():
                specs[side] = {}
                for u in USERS:
                    c = d.connect(u)
                    scene = common.cornell(c, RES)
                    ref_blob, _ = common.reference(c, scene, 64, settings.work)
                    specs[side][u] = common.wall_spec(scene, ref_blob, iterations=iterations,
                                                      spp=SPP)
                    c.close()
                burst(d, specs[side], side)  # warm-up: every worker compiles its kernels
            listing = {side: d.client.server.GetServerInfo(pb.GetServerInfoRequest()).workers
                       for side, d in daemons.items()}

            def measure(side: str, r: int) -> None:
                row = burst(daemons[side], specs[side], side)
                figures[side].append(row)
                rows.append({"round": r, **row})

            common.alternate(rounds, lambda r: measure("one", r),
                             lambda r: measure("packed", r))
            cuda = one.cuda
    ratios = [b["iterations_per_second"] / a["iterations_per_second"]
              for a, b in zip(figures["one"], figures["packed"])]
    ratio = common.median(ratios)
    csv = common.write_csv(settings.out / "gpu_packing.csv", rows)
    device = listing["one"][0].device if listing["one"] else "?"
    sizing = listing["packed"][0].sizing if listing["packed"] else ""

    def per(side: str, key: str, scale: float = 1, fmt: str = "{:.1f}") -> str:
        return common.spread([f[key] * scale for f in figures[side]], fmt)

    what = (f"total iterations per second, {len(USERS) * JOBS_PER_USER} small jobs of "
            f"{len(USERS)} users, {len(listing['packed'])} workers ({'auto' if cuda else '2'}) "
            f"/ one worker on {device}")
    target = Target(f"{what} (target >= {TARGET:g} on an H100-class GPU)", f"{ratio:.2f}",
                    ratio >= TARGET) if cuda else \
        Target(f"{what} (no target on the CPU: its cores are the limit)", f"{ratio:.3f}", None)
    return Result("gpu_packing", "Many small jobs on one device", [target], [
        f"Jobs: {len(USERS)} users x {JOBS_PER_USER} Cornell box walls, {RES}x{RES}, {SPP} spp, "
        f"{iterations} iterations each, started together; {rounds} alternating rounds after a "
        "warm-up round on each daemon.",
        f"- packed: {sizing or len(listing['packed'])}",
        f"- one worker: {per('one', 'iterations_per_second')} iterations/s; packed: "
        f"{per('packed', 'iterations_per_second')} iterations/s",
        f"- ratio per round: {', '.join(f'{x:.3f}' for x in ratios)}",
        f"- workers' CPU per iteration: one {per('one', 'worker_cpu_seconds_per_iteration', 1000, '{:.0f}')}"
        f" ms, packed {per('packed', 'worker_cpu_seconds_per_iteration', 1000, '{:.0f}')} ms",
    ], [csv], time.perf_counter() - began)
