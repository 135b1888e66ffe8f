"""Workers per device: as many as a GPU's free memory holds for the largest job admission lets
in (simulated readings), or as many as asked; a CPU-only host keeps one unless told. And a
daemon with two CPU workers on one device, through real processes: both shown by `matopt
info`, both rendering, two users' jobs at once."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from matopt_api.v1 import matopt_pb2 as pb
from matoptd.workers import devices, sizing

from conftest import Daemon, Stubs, TOKENS, token_file, wait_iteration, wait_state
from test_faults import cornell_job

GiB = 1 << 30
DEFAULT_SAMPLES = 1 << 26  # matoptd --max-samples


def test_auto_fits_workers_to_the_free_memory():
    per = sizing.per_worker(DEFAULT_SAMPLES)
    assert per == 5 * GiB  # 1 GiB at rest, 64 bytes for each of 2^26 samples
    assert sizing.for_device(24 * GiB, DEFAULT_SAMPLES, None).count == 4   # 0.9 * 24 // 5
    assert sizing.for_device(79 * GiB, DEFAULT_SAMPLES, None).count == 8   # at most 8
    assert sizing.for_device(79 * GiB, 1 << 22, None).count == 8
    assert sizing.for_device(12 * GiB, 1 << 22, None).count == 8           # small jobs pack
    assert sizing.for_device(12 * GiB, DEFAULT_SAMPLES, None).count == 2
    small = sizing.for_device(3 * GiB, DEFAULT_SAMPLES, None)
    assert small.count == 1 and "not even one fits" in small.why
    assert sizing.for_device(None, DEFAULT_SAMPLES, None).count == 1
    assert sizing.for_device(79 * GiB, DEFAULT_SAMPLES, 3).count == 3       # as asked
    why = sizing.for_device(24 * GiB, DEFAULT_SAMPLES, None).why
    assert why == ("4 per device (auto: 24.0 GiB free, 5.0 GiB per worker for a render call "
                   "of up to 67,108,864 samples)")


def test_parse_takes_auto_or_a_positive_number():
    assert sizing.parse("auto") is None and sizing.parse("3") == 3
    for bad in ("0", "-1", "many"):
        with pytest.raises(ValueError):
            sizing.parse(bad)


def test_each_gpu_gets_the_workers_its_own_memory_holds():
    free = {"0": 79 * GiB, "1": 11 * GiB}.get
    places = devices.placements(["0", "1"], None, None, [0, 1], None, DEFAULT_SAMPLES, free)
    assert [p.cuda for p in places] == ["0"] * 8 + ["1"] * 1
    assert places[0].sizing.startswith("8 per device (auto: 79.0 GiB free")
    asked = devices.placements(["0"], None, None, [0, 1], 2, DEFAULT_SAMPLES, free)
    assert [p.cuda for p in asked] == ["0", "0"]
    named_twice = devices.placements(["0", "0"], None, None, [0, 1], None, DEFAULT_SAMPLES, free)
    assert [p.cuda for p in named_twice] == ["0", "0"]  # --devices 0,0 as before


def test_a_count_asked_for_does_not_read_the_free_memory():
    """`matopt demo`'s private daemon asks for one worker; nvidia-smi is not run for it."""
    def unread(device):
        raise AssertionError(f"free memory of {device} read")
    places = devices.placements(["0"], None, None, [0, 1], 1, DEFAULT_SAMPLES, unread)
    assert [p.cuda for p in places] == ["0"]


def test_a_cpu_only_host_keeps_one_worker_unless_told():
    assert [(p.cuda, p.cores, p.sizing) for p in devices.placements(
        [], None, "llvm_ad_rgb", [0, 1])] == [(None, (0, 1), "")]
    two = devices.placements([], None, "llvm_ad_rgb", [0, 1], 2)
    assert [(p.cores, p.threads) for p in two] == [((0, 1), 2)] * 2  # both on every core
    assert two[0].sizing == "2 sharing the CPU's cores (--workers-per-device 2)"
    split = devices.placements([], 2, "llvm_ad_rgb", [0, 1])  # --workers 2: cores split
    assert [p.cores for p in split] == [(0,), (1,)]


def test_two_cpu_workers_on_one_device_share_two_users_jobs(tmp_path):
    d = Daemon(tmp_path / "data", token_file(tmp_path), "--workers-per-device", "2").start()
    alice, bob = Stubs(d.address, TOKENS["alice"]), Stubs(d.address, TOKENS["bob"])
    try:
        env = dict(os.environ, MATOPT_SERVER=d.address, MATOPT_TOKEN=TOKENS["alice"])
        info = subprocess.run([sys.executable, "-m", "matopt_client.cli", "info"], env=env,
                              capture_output=True, text=True, timeout=120)
        assert info.returncode == 0, info.stderr
        assert "2 sharing the CPU's cores (--workers-per-device 2)" in info.stdout
        assert "workers/0" in info.stdout and "workers/1" in info.stdout
        # Long enough that neither ends before it is cancelled (frozen, 400 took 6 s).
        a, b = cornell_job(alice, 5000), cornell_job(bob, 5000)
        deadline, busy = time.time() + 120, set()
        while time.time() < deadline and len(busy) < 2:  # both workers hold a job at once
            listing = alice.server.GetServerInfo(pb.GetServerInfoRequest()).workers
            if all(w.job_count == 1 for w in listing):
                busy = {w.name for w in listing}
            time.sleep(0.05)
        assert busy == {"workers/0", "workers/1"}
        for stubs, job in ((alice, a), (bob, b)):  # both go on
            wait_iteration(stubs, job.name, 2, timeout=300)
        for stubs, job in ((alice, a), (bob, b)):
            stubs.jobs.CancelJob(pb.CancelJobRequest(name=job.name))
        for stubs, job in ((alice, a), (bob, b)):
            wait_state(stubs, job.name, (pb.JOB_STATE_CANCELLED,), timeout=120)
    finally:
        alice.close()
        bob.close()
        d.stop()
