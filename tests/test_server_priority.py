"""On cores the server shares with its workers, rendering goes first: the daemon's server
threads run ``--server-nice`` levels below the workers (by default the lowest, 19, beside CPU
workers), whose processes (restarted ones too) keep the nice value the daemon was started
with. A real daemon, read from /proc."""

from __future__ import annotations

import os
import signal
import time

import grpc
import pytest

from matopt_api.v1 import matopt_pb2 as pb
from matoptd.main import SERVER_NICE, SERVER_NICE_SHARED, server_nice

from conftest import Daemon, Stubs
from test_faults import wait_worker

BY = 3


def nice(pid: int, tid: int | None = None) -> int:
    stat = open(f"/proc/{pid}/task/{tid or pid}/stat").read()
    return int(stat.rsplit(")", 1)[1].split()[16])


@pytest.fixture
def daemon(tmp_path):
    base = os.getpriority(os.PRIO_PROCESS, 0)
    if base + BY > 19:
        pytest.skip(f"started at nice {base}: no lower priority is left for the server")
    d = Daemon(tmp_path / "data", None, "--server-nice", str(BY)).start()
    yield d, base
    d.stop()


def test_the_server_runs_below_its_workers_and_restarted_ones_too(daemon):
    d, base = daemon
    stubs = Stubs(d.address)
    try:
        assert nice(d.proc.pid) == base + BY  # the main thread: asyncio, the handlers
        first = wait_worker(stubs, (pb.WORKER_STATE_IDLE,))
        assert nice(first.pid) == base
        os.kill(first.pid, signal.SIGKILL)
        try:  # the next task finds the worker gone: its lane starts another
            stubs.scenes.CreateScene(pb.CreateSceneRequest())
        except grpc.RpcError:
            pass
        restarted = wait_worker(stubs, (pb.WORKER_STATE_IDLE,))
        while restarted.pid in (0, first.pid):
            time.sleep(0.1)
            restarted = wait_worker(stubs, (pb.WORKER_STATE_IDLE,))
        assert nice(restarted.pid) == base  # started again by its lane
        threads = {int(t): nice(d.proc.pid, int(t))
                   for t in os.listdir(f"/proc/{d.proc.pid}/task")}
        assert sorted(set(threads.values())) == [base, base + BY]  # lanes, and the rest
    finally:
        stubs.close()


def test_by_default_the_server_goes_lowest_where_cpu_workers_share_its_cores(tmp_path):
    """Beside CPU workers on its own cores the server runs at nice 19 (its calls wait for the
    render); a given level wins, and beside GPU workers or with cores of its own it is 10."""
    assert server_nice(None, True) == SERVER_NICE_SHARED == 19
    assert server_nice(None, False) == SERVER_NICE == 10
    assert server_nice(3, True) == 3 and server_nice(0, True) == 0
    d = Daemon(tmp_path / "data", None).start()  # this machine's one CPU worker
    try:
        stubs = Stubs(d.address)
        worker = wait_worker(stubs, (pb.WORKER_STATE_IDLE,))
        base = nice(worker.pid)
        assert nice(d.proc.pid) == min(19, base + SERVER_NICE_SHARED)
        stubs.close()
    finally:
        d.stop()
