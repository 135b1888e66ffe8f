"""Warm start: how soon a job's first iteration ends on a daemon that has run the scene before,
against a fresh Python process doing the same (import Mitsuba, set the variant, load the scene,
one whole iteration: render, loss, backward, Adam step).

This is what a long-running daemon is for: Mitsuba's import, the variant's initialisation and
the compiled kernels are already in memory. What it cannot remove is the iteration itself
(render, backward pass, step): both sides pay it, so the ratio is bounded by (setup +
iteration) / iteration. Both sides count the first iteration as finished once its loss is
known and its gradient step is launched: the LLVM backend runs kernels asynchronously, and
the step completes while the next iteration is traced (the daemon reports iteration 0 at that
point; the fresh process's clock stops there too). The fresh process is given a warm Dr.Jit kernel
cache on disk (one run first, not counted), the best case for a script that has run before;
one cold-cache run is shown for context. The daemon's time runs from CreateJob sent to the
WatchJob event of iteration 0 received; the fresh process's from its start to the end of its
first iteration. Rounds alternate.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import common
from common import Result, Settings, Target

RES, SPP = 128, 4
TARGET = 5.0  # fresh process time / daemon time


def fresh_process(variant: str, ref_path: Path, cache: Path) -> dict[str, float]:
    """Runs plain.py --first-iteration in a new interpreter; times from just before exec."""
    env = dict(os.environ, DRJIT_CACHE_DIR=str(cache))
    if variant.startswith("llvm") and "DRJIT_LIBLLVM_PATH" not in env:
        from matoptd.engine.variant import find_libllvm
        env["DRJIT_LIBLLVM_PATH"] = find_libllvm() or ""
    command = [sys.executable, str(Path(__file__).with_name("plain.py")), "--first-iteration",
               "--variant", variant, "--xml", str(common.CORNELL_XML), "--reference",
               str(ref_path), "--set", f"resx={RES}", "--set", f"resy={RES}", "--spp", str(SPP),
               "--start", *map(str, common.GREY), "--integrator", "prb", "--max-depth", "8"]
    for key in common.WALLS:
        command += ["--key", key]
    began = time.time()
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    if done.returncode != 0:
        raise RuntimeError(f"fresh process failed: {done.stderr[-2000:]}")
    t = json.loads(done.stdout.strip().splitlines()[-1])
    return {"total": t["first_iteration"] - began, "interpreter": t["started"] - began,
            "import": t["imported"] - t["started"], "variant": t["variant_set"] - t["imported"],
            "load": t["loaded"] - t["variant_set"],
            "first_iteration": t["first_iteration"] - t["loaded"]}


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    rounds = 1 if settings.quick else 3
    client = server.client
    scene = common.cornell(client, RES)
    ref_blob, ref_path = common.reference(client, scene, 64, settings.work)
    spec = common.wall_spec(scene, ref_blob, iterations=3, spp=SPP)
    common.require_success(common.run_job(client, spec), "warm_start warm-up")  # has run it

    cache = settings.work / "fresh-kernel-cache"
    cold = fresh_process(server.variant, ref_path, cache)  # empty cache; fills it
    rows = [{"round": -1, "method": "fresh process, cold kernel cache", **cold}]
    daemon_s: list[float] = []
    fresh_s: list[float] = []
    steady: list[float] = []  # the daemon's later iterations: a floor for the first one

    def daemon(r: int) -> None:
        run_ = common.run_job(client, spec)
        common.require_success(run_, "warm_start")
        daemon_s.append(run_.first_iteration)
        steady.append(common.per_iteration(run_.seconds))
        rows.append({"round": r, "method": "daemon", "total": run_.first_iteration,
                     "first_iteration": run_.seconds[0], "steady_iteration": steady[-1]})

    def fresh(r: int) -> None:
        t = fresh_process(server.variant, ref_path, cache)
        fresh_s.append(t["total"])
        rows.append({"round": r, "method": "fresh process", **t})

    common.alternate(rounds, daemon, fresh)
    ratios = [f / d for f, d in zip(fresh_s, daemon_s)]
    ratio = common.median(ratios)
    parts = [r for r in rows if r["method"] == "fresh process"][-1]

    csv = common.write_csv(settings.out / "warm_start.csv", rows)
    return Result("warm_start", "Warm start", [
        Target("fresh process / daemon, CreateJob to first iteration",
               f"{ratio:.1f}x (target >= {TARGET:g}x)", ratio >= TARGET),
    ], [
        f"Cornell box walls, {RES}x{RES}, {SPP} spp; {rounds} alternating round(s).",
        f"- daemon, CreateJob to iteration 0 received: "
        f"{common.spread([s * 1000 for s in daemon_s], '{:.0f}')} ms",
        f"- fresh process (warm kernel cache on disk): {common.spread(fresh_s, '{:.2f}')} s; "
        f"of the last: interpreter {parts['interpreter']:.2f} s, import mitsuba "
        f"{parts['import']:.2f} s, set variant {parts['variant']:.2f} s, load scene "
        f"{parts['load']:.2f} s, first iteration {parts['first_iteration']:.2f} s",
        f"- fresh process with an empty kernel cache (once): {cold['total']:.2f} s "
        f"(first iteration {cold['first_iteration']:.2f} s)",
        f"- one later iteration of the same job on the daemon, from one report to the next "
        f"(its backward pass included): {common.spread([s * 1000 for s in steady], '{:.0f}')} "
        "ms. The fresh process spends "
        f"{common.median([r['total'] - r['first_iteration'] for r in rows if r['method'] == 'fresh process']) * 1000:.0f}"
        " ms before its first iteration starts; the daemon's whole time to a first iteration "
        "is the figure above.",
    ], [csv], time.perf_counter() - began)
