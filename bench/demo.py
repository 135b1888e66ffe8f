"""The demo's time: ``matopt demo`` from the command to its table, as a new user first sees it.

The command starts a private daemon (no daemon answers at the default address), renders the
reference, runs the job (the Cornell box's three walls from grey, 128x128, 4 spp, 100
iterations) and exports it; the time is the whole command's wall clock, the daemon's start
included. Target: under 5 s. Each run's private daemon has a fresh data directory, so its
kernels come from Dr.Jit's cache on disk (shared by the runs: the first fills it, once, and is
shown apart). --quick: 32 px and 10 iterations, one run after the first.

The command's own notes on stderr, stamped as they arrive, split the time: the private
daemon's start, the scene and its reference, the job (its iterations by its own clock, from
the exported history.csv, and the rest: its start and its end, the standard errors and the
result images), and the export with the daemon's stop.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
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
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env=env)
    stamps: dict[str, float] = {}
    err: list[str] = []

    def notes() -> None:  # each phase's note, stamped as it arrives
        for line in process.stderr:
            err.append(line)
            for phase, marker in MARKERS.items():
                if marker in line and phase not in stamps:
                    stamps[phase] = time.perf_counter() - began

    reader = threading.Thread(target=notes, daemon=True)
    reader.start()
    timer = threading.Timer(300, process.kill)
    timer.start()
    stdout = process.stdout.read()
    process.wait()
    timer.cancel()
    reader.join(10)
    seconds = time.perf_counter() - began
    if process.returncode != 0:
        raise RuntimeError(f"matopt demo failed: {''.join(err)[-2000:]}")
    answer = json.loads(stdout)
    row = {"run": k, "seconds": seconds, "max_abs_error": answer["maxAbsError"]}
    history = out / "history.csv"
    iterations = float(history.read_text().strip().splitlines()[-1].split(",")[1])
    ends = [stamps.get(p, math.nan) for p in MARKERS] + [seconds]
    row |= {"daemon_start": ends[0], "scene_and_reference": ends[1] - ends[0],
            "job": ends[2] - ends[1], "job_iterations": iterations,
            "export_and_stop": ends[3] - ends[2]}
    return row


# The notes that end each phase (matopt_client/cli/demo.py and progress.py say them).
MARKERS = {"daemon": "private matoptd ready", "reference": "started ", "job": "SUCCEEDED"}
PHASES = [("daemon_start", "the private daemon's start"),
          ("scene_and_reference", "the scene and its 256-spp reference"),
          ("job", "the job"), ("job_iterations", "of which its iterations (its clock)"),
          ("export_and_stop", "the export and the daemon's stop")]


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
        "- where the later runs' time goes (s): " + "; ".join(
            f"{what} {common.spread([r[key] for r in rows[1:]], '{:.2f}')}"
            for key, what in PHASES),
    ], [csv], time.perf_counter() - began)
