"""Where the daemon's processes run: ``--server-cores`` keeps the server off the workers' cores."""

from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import Daemon, Stubs

CORES = sorted(os.sched_getaffinity(0))


def thread_affinities(pid: int) -> set[frozenset[int]]:
    """The CPU sets of every thread of a process."""
    return {frozenset(os.sched_getaffinity(int(t))) for t in os.listdir(f"/proc/{pid}/task")}


@pytest.mark.skipif(len(CORES) < 2, reason="needs at least 2 cores to split")
def test_server_cores_keep_the_server_and_the_worker_apart(tmp_path: Path):
    daemon = Daemon(tmp_path / "data", None, "--server-cores", "1").start()
    try:
        stubs = Stubs(daemon.address)
        worker = stubs.server.GetServerInfo(pb.GetServerInfoRequest()).workers[0]
        assert thread_affinities(daemon.proc.pid) == {frozenset(CORES[:1])}
        assert thread_affinities(worker.pid) == {frozenset(CORES[1:])}
        # numpy's BLAS on one thread in the worker: its threads would fight the render's
        environ = open(f"/proc/{worker.pid}/environ", "rb").read().split(b"\0")
        assert b"OPENBLAS_NUM_THREADS=1" in environ or "OPENBLAS_NUM_THREADS" in os.environ
        assert worker.threads == len(CORES) - 1
        stubs.close()
    finally:
        daemon.stop()


def test_server_cores_that_leave_the_workers_none_are_refused(tmp_path: Path):
    daemon = Daemon(tmp_path / "data", None, "--server-cores", str(len(CORES)))
    with pytest.raises(RuntimeError, match=rf"--server-cores: {len(CORES)} core\(s\) for the "
                                           rf"server leave none of the {len(CORES)}"):
        daemon.start()


def _node(node_id: str, alive: bool = True, **resources: float) -> dict:
    return {"NodeID": node_id, "Alive": alive, "NodeManagerAddress": "10.0.0.1",
            "Resources": {"memory": 10e9, **resources}}


def test_a_ray_cluster_gets_one_worker_per_gpu_and_none_on_a_node_without():
    ray_workers = pytest.importorskip("matoptd.workers.ray_cluster")
    nodes = [_node("aaaa1111", CPU=8, GPU=2), _node("bbbb2222", CPU=4),
             _node("cccc3333", alive=False, CPU=8, GPU=1)]
    slots = ray_workers.slots(nodes, cpu_workers=None)
    assert [(s.name, s.gpu, s.threads) for s in slots] == [
        ("workers/aaaa1111-0", True, 4), ("workers/aaaa1111-1", True, 4)]
    assert slots[0].memory == int(0.8 * 10e9 / 2)  # the node's memory, shared by its workers


def test_a_ray_cluster_without_gpus_gets_cpu_workers_per_node():
    ray_workers = pytest.importorskip("matoptd.workers.ray_cluster")
    nodes = [_node("aaaa1111", CPU=8), _node("bbbb2222", CPU=3)]
    slots = ray_workers.slots(nodes, cpu_workers=2, memory_limit=1 << 30)
    assert [(s.name, s.gpu, s.threads, s.memory) for s in slots] == [
        ("workers/aaaa1111-0", False, 4, 1 << 30), ("workers/aaaa1111-1", False, 4, 1 << 30),
        ("workers/bbbb2222-0", False, 1, 1 << 30), ("workers/bbbb2222-1", False, 1, 1 << 30)]


def test_the_cluster_watch_adds_the_workers_of_a_node_that_joins_and_retires_a_leavers():
    ray_workers = pytest.importorskip("matoptd.workers.ray_cluster")
    known: dict = {}
    retired: list[tuple[str, str]] = []

    def make(slot):
        return SimpleNamespace(name=slot.name, node=slot.node, gone=False, info={})

    watch = ray_workers.ClusterWatch(make, lambda w: known.__setitem__(w.name, w),
                                     lambda name, why: retired.append((name, why)),
                                     lambda: dict(known), cpu_workers=None, memory_limit=None)
    watch.reconcile([_node("aaaa1111", CPU=2, GPU=1)])
    assert list(known) == ["workers/aaaa1111-0"]
    watch.reconcile([_node("aaaa1111", alive=False, CPU=2, GPU=1), _node("bbbb2222", GPU=1)])
    assert list(known) == ["workers/aaaa1111-0", "workers/bbbb2222-0"]
    assert retired == [("workers/aaaa1111-0", "its node (aaaa1111) left the cluster")]
