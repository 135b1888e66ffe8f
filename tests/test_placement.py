"""Where the daemon's processes run: ``--server-cores`` keeps the server off the workers' cores."""

from __future__ import annotations

import os
from pathlib import Path

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
        assert worker.threads == len(CORES) - 1
        stubs.close()
    finally:
        daemon.stop()


def test_server_cores_that_leave_the_workers_none_are_refused(tmp_path: Path):
    daemon = Daemon(tmp_path / "data", None, "--server-cores", str(len(CORES)))
    with pytest.raises(RuntimeError, match=rf"--server-cores: {len(CORES)} core\(s\) for the "
                                           rf"server leave none of the {len(CORES)}"):
        daemon.start()
