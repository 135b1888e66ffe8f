"""The demo's time: ``matopt demo`` from the command to its table, as a new user first sees it.

The command starts a private daemon (no daemon answers at the default address), renders the
reference, runs the job (the Cornell box's three walls from grey, 128x128, 4 spp, 100
iterations) and exports it; the time is the whole command's wall clock, the daemon's start
included. Target: under 5 s. Each run's private daemon has a fresh data directory, so its
kernels come from Dr.Jit's cache on disk (shared by the runs: the first fills it, once, and is
shown apart). --quick: 32 px and 10 iterations, one run after the first.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import common
from common import Result, Settings, Target

TARGET = 5.0  # seconds
NEEDS_DAEMON = False  # the demo starts its own


def once(settings: Settings, k: int) -> dict:
    out = settings.work / f"demo-{k}"
    command = [sys.executable, "-m", "matopt_client.cli", "--server", "127.0.0.1:1", "demo",
               "--json", "--out", str(out)]
    if settings.quick:
        command += ["--resolution", "32", "--iterations", "10"]
    env = dict(os.environ, DRJIT_CACHE_DIR=str(settings.work / "demo-kernel-cache"))
    if settings.variant:
        env["MATOPTD_VARIANT"] = settings.variant  # the private daemon reads it
    began = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    seconds = time.perf_counter() - began
    if done.returncode != 0:
        raise RuntimeError(f"matopt demo failed: {done.stderr[-2000:]}")
    answer = json.loads(done.stdout)
    return {"run": k, "seconds": seconds, "max_abs_error": answer["maxAbsError"]}


def run(settings: Settings, server: None) -> Result:
    began = time.perf_counter()
    rows = [once(settings, k) for k in range(2 if settings.quick else 4)]
    warm = [r["seconds"] for r in rows[1:]]
    median = common.median(warm)
    csv = common.write_csv(settings.out / "demo.csv", rows)
    return Result("demo", "The demo's time", [
        Target("`matopt demo`, command to result (median, kernel cache warm)",
               f"{median:.1f} s (target < {TARGET:g} s)", median < TARGET),
    ], [
        f"`matopt demo --json`{' --resolution 32 --iterations 10' if settings.quick else ''}, "
        "a private daemon each time; wall clock of the whole command.",
        f"- first run (empty kernel cache): {rows[0]['seconds']:.1f} s",
        f"- later runs: {common.spread(warm, '{:.1f}')} s",
        f"- max abs error of the walls: {common.spread([r['max_abs_error'] for r in rows])}",
    ], [csv], time.perf_counter() - began)
