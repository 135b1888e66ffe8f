"""Workers as Ray actors (``matoptd --ray``) against local worker processes.

A Ray cluster of this machine from Ray's own harness (``ray.cluster_utils.Cluster``): a head
without GPU and "machines" that each declare one GPU, so the daemon runs one worker per
machine (on the variant the local daemon picked: the CPU backend here, CUDA on a GPU host).

1. Per-iteration overhead: the same job (Cornell box walls, constant rate) on the case's local
   daemon (one worker process with every core) and on a Ray daemon with one machine (one
   actor, as many threads), alternating. Every message between the daemon and the engine is
   a Ray call instead of a socket write, and blobs go through Ray's object store.
2. Throughput: two jobs started together on the Ray daemon with one machine, then with a
   second machine added (a second worker), alternating (the machine joins and leaves between
   rounds, as machines of a real cluster do). On one host the two "machines" share its cores
   (or its GPU), so this measures what spreading costs or gains there, not the scaling of
   real machines, which each bring their own device.
"""

from __future__ import annotations

import os
import time

import common
from common import Result, Settings, Target
from matopt_api.v1 import matopt_pb2 as pb
from two_workers import pair

RES, SPP = 64, 4


def workers_ready(d: common.Daemon, count: int, timeout: float = 300) -> list[pb.Worker]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        listed = d.client.server.GetServerInfo(pb.GetServerInfoRequest()).workers
        if len(listed) == count and all(w.state == pb.WORKER_STATE_IDLE for w in listed):
            return list(listed)
        time.sleep(0.2)
    raise RuntimeError(f"the Ray daemon did not get {count} idle worker(s) in {timeout} s")


def one_job(d: common.Daemon, spec: pb.JobSpec, what: str) -> dict:
    run = common.run_job(d.client, spec)
    common.require_success(run, f"ray_cluster {what}")
    n = len(run.arrivals)
    return {"side": what, "job_seconds_per_iteration": common.per_iteration(run.seconds),
            "client_seconds_per_iteration": (run.arrivals[-1] - run.arrivals[0]) / (n - 1)}


def run(settings: Settings, server: common.Daemon) -> Result:
    from ray.cluster_utils import Cluster

    began = time.perf_counter()
    iterations, rounds = (20, 2) if settings.quick else (100, 4)
    cores = len(os.sched_getaffinity(0))
    machine = {"num_cpus": cores, "num_gpus": 1}
    cluster = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 1, "num_gpus": 0, "include_dashboard": False,
        "_system_config": {"health_check_period_ms": 500,
                           "health_check_failure_threshold": 4}})
    rows: list[dict] = []
    try:
        cluster.add_node(**machine)
        with common.daemon(settings.work, "ray", ["--ray", cluster.address,
                                                  "--variant", server.variant]) as ray_d:
            workers_ready(ray_d, 1)
            specs = {}
            for side, d in (("local", server), ("ray", ray_d)):
                scene = common.cornell(d.client, RES)
                ref_blob, _ = common.reference(d.client, scene, 64, settings.work)
                specs[side] = common.wall_spec(scene, ref_blob, iterations=iterations, spp=SPP)
                one_job(d, specs[side], side)  # warm-up: kernels compiled

            single: dict[str, list[dict]] = {"local": [], "ray": []}

            def measure(side: str, r: int) -> None:
                row = one_job(server if side == "local" else ray_d, specs[side], side)
                single[side].append(row)
                rows.append({"measure": "overhead", "round": r, **row})

            common.alternate(rounds, lambda r: measure("local", r),
                             lambda r: measure("ray", r))

            spread: dict[str, list[dict]] = {"one": [], "two": []}
            second: list = []

            def machines(count: int, r: int) -> None:
                while len(second) < count - 1:
                    second.append(cluster.add_node(**machine))
                while len(second) > count - 1:
                    cluster.remove_node(second.pop())
                workers_ready(ray_d, count)
                side = "one" if count == 1 else "two"
                row = pair(ray_d, specs["ray"], f"{side} machine(s)")
                spread[side].append(row)
                rows.append({"measure": "throughput", "round": r, "machines": count, **row})

            pair(ray_d, specs["ray"], "warm-up")
            common.alternate(rounds, lambda r: machines(1, r), lambda r: machines(2, r))
    finally:
        cluster.shutdown()

    def ratio_of(key: str) -> list[float]:
        return [b[key] / a[key] for a, b in zip(single["local"], single["ray"])]

    job_ratios = ratio_of("job_seconds_per_iteration")
    client_ratios = ratio_of("client_seconds_per_iteration")
    throughput = [b["iterations_per_second"] / a["iterations_per_second"]
                  for a, b in zip(spread["one"], spread["two"])]
    csv = common.write_csv(settings.out / "ray_cluster.csv", rows)

    def ms(side: str, key: str) -> str:
        return common.spread([row[key] * 1000 for row in single[side]], "{:.1f}")

    return Result("ray_cluster", "Workers as Ray actors", [
        Target("time per iteration, Ray actor / local worker process, as the job records it "
               "(no target)", common.spread(job_ratios), None),
        Target("time per iteration, Ray actor / local worker process, as the client sees it "
               "(no target)", common.spread(client_ratios), None),
        Target("iterations per second of two jobs at once, two machines / one, on one host "
               "(no target)", common.spread(throughput), None),
    ], [
        f"Jobs: Cornell box walls, {RES}x{RES}, {SPP} spp, {iterations} iterations, "
        f"{rounds} alternating rounds after warm-up; Ray machines of {cores} CPU(s) and one "
        "declared GPU each, on this host.",
        f"- local worker: {ms('local', 'job_seconds_per_iteration')} ms per iteration "
        f"(client: {ms('local', 'client_seconds_per_iteration')} ms)",
        f"- Ray actor: {ms('ray', 'job_seconds_per_iteration')} ms per iteration "
        f"(client: {ms('ray', 'client_seconds_per_iteration')} ms)",
        "- two jobs on one machine: " + common.spread(
            [f["iterations_per_second"] for f in spread["one"]], "{:.1f}") +
        " iterations/s; on two: " + common.spread(
            [f["iterations_per_second"] for f in spread["two"]], "{:.1f}") + " iterations/s",
    ], [csv], time.perf_counter() - began)
