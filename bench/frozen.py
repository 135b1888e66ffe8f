"""Frozen iterations: the daemon's iteration with the ``frozen`` choice on (render, loss and
backward pass recorded once with dr.freeze and replayed), with it off, and a plain Mitsuba
loop, at equal work.

1. The Cornell box: overhead's job (the red and green walls from grey, MSE, Adam 0.03
   constant, 4 spp, prb at the scene's depth 8, the same seeds on all three sides) at 32x32,
   64x64 and 128x96. Per-iteration time is steady state from the daemon's history
   (iteration 0 out; the frozen job's second recording, at iteration 1, in). Not on a GPU,
   where bench/overhead.py times the same job.
2. The thesis's Table 2 and Table 4 scenes (``--thesis-repo``; skipped when absent) at 32x24,
   64x48 and 128x96, jobs of the thesis's 100 iterations (on a GPU: Table 2 alone at its own
   683x512, jobs of 10 iterations, one round): the daemon's defaults
   (every choice as it comes: eta's differences, the standard errors at the end) at the plain
   loop's spp against the plain loop of bench/real_scenes.py. Here the daemon's time is its
   whole job from iteration 0's end to the job's end, so the defaults' own extra work
   (differences, J's passes) counts, and so do its result images (64 spp renders the plain loop
   never makes). The parts are reported apart: the iterations (differences in), and the job's
   end (J, then the result renders). The defaults reach parameters where these scenes cost more
   to render than where the plain loop goes, so a fourth side takes the plain loop's own steps
   (the plain preset) frozen: equal work, the same trajectory, the machinery's figure.

Each size runs three rounds after a warm-up of each side (kernels compiled); within a round
the sides take turns, their order rotated from round to round. Ratios are per round, then
the median.
"""

from __future__ import annotations

import re
import sys
import time
import uuid
from typing import Callable

import common
import plain
import real_scenes
from common import Result, Settings, Target
from matopt_api.v1 import matopt_pb2 as pb

DAEMON = real_scenes.DAEMON  # its 1024-spp references at 683x512 in one render call
SIZES = [(32, 32), (64, 64), (128, 96)]
THESIS_SIZES = [(32, 24), (64, 48), (128, 96)]
# On a GPU the figure owed is Table 2 at the thesis's own size; the case's share of a device
# loan (bench/gpu_run.py) holds that one cell, one round after the warm-up, short jobs.
GPU_TABLES, GPU_SIZES, GPU_ITERATIONS, GPU_ROUNDS = ("table2",), [(683, 512)], 10, 1
SPP = 4
# Targets against the plain loop by film width, on the Cornell box and the thesis's scenes (CPU).
TARGETS = {32: 0.5, 128: 0.8}
EQUAL_WORK = "plain steps, frozen"  # the plain preset (the plain loop's steps), frozen


Side = Callable[[int], tuple[float, float]]  # round -> (seconds per iteration, last loss)


def _rounds(sides: dict[str, Side], rounds: int) -> tuple[dict[str, list[float]],
                                                          dict[str, list[float]]]:
    """Each side once to warm up, then ``rounds`` rounds in rotated order: per side, its
    seconds per iteration and last loss of each round."""
    times: dict[str, list[float]] = {m: [] for m in sides}
    losses: dict[str, list[float]] = {m: [] for m in sides}
    for side in sides.values():
        side(-1)
    names = list(sides)
    for r in range(rounds):
        for name in names[r % len(names):] + names[:r % len(names)]:
            seconds, loss = sides[name](r)
            times[name].append(seconds)
            losses[name].append(loss)
    return times, losses


def _ratio(times: dict[str, list[float]], a: str, b: str) -> float:
    return common.median([x / y for x, y in zip(times[a], times[b])])


def _cornell(settings: Settings, server: common.Daemon, iterations: int, rounds: int,
             rows: list[dict], targets: list[Target], lines: list[str]) -> None:
    client = server.client
    lines.append(f"Cornell box walls from grey, {SPP} spp, {iterations} iterations, Adam 0.03 "
                 f"constant, MSE, prb depth 8 on all sides, the same seeds; {rounds} rounds "
                 "after a warm-up of each side, order rotated; ms per iteration (median) and "
                 "ratios per round (median).")
    for width, height in SIZES:
        size = f"{width}x{height}"
        scene = client.scenes.CreateScene(pb.CreateSceneRequest(
            overrides={"resx": str(width), "resy": str(height)}, request_id=str(uuid.uuid4())))
        ref_blob, ref_path = common.reference(client, scene, 64, settings.work)
        baseline = plain.PlainSpec(common.CORNELL_XML, ref_path,
                                   {k: common.GREY for k in common.WALLS}, iterations, SPP,
                                   "prb", 8, overrides={"resx": str(width), "resy": str(height)})

        def job(frozen: str) -> Side:
            def side(r: int) -> tuple[float, float]:
                spec = common.wall_spec(scene, ref_blob, iterations=iterations, spp=SPP, seed=0)
                spec.choices["frozen"] = frozen
                done = common.run_job(client, spec, server=server)
                common.require_success(done, "frozen")
                return _row(rows, "cornell", size, "frozen" if frozen == "on" else "unfrozen",
                            r, common.per_iteration(done.seconds), done.history[-1].loss)
            return side

        def loop(r: int) -> tuple[float, float]:
            its = plain.run(baseline, server.variant)
            return _row(rows, "cornell", size, "plain", r,
                        common.per_iteration([it.seconds for it in its]), its[-1].loss)

        times, losses = _rounds({"frozen": job("on"), "unfrozen": job("off"), "plain": loop},
                                rounds)
        frozen_plain = _ratio(times, "frozen", "plain")
        unfrozen_plain = _ratio(times, "unfrozen", "plain")
        frozen_unfrozen = _ratio(times, "frozen", "unfrozen")
        same = all(abs(a - b) <= 1e-4 * abs(b) for a, b in zip(losses["frozen"],
                                                               losses["unfrozen"]))
        target = TARGETS.get(width)
        targets.append(Target(f"Cornell box {size}: frozen / plain loop"
                              + (f" (<= {target}, CPU)" if target else ""),
                              f"{frozen_plain:.2f} (unfrozen / plain {unfrozen_plain:.2f}, "
                              f"frozen / unfrozen {frozen_unfrozen:.2f})",
                              None if target is None else frozen_plain <= target))
        ms = {m: common.median(t) * 1000 for m, t in times.items()}
        lines.append(f"- {size}: frozen {ms['frozen']:.1f} ms, unfrozen "
                     f"{ms['unfrozen']:.1f} ms, plain loop {ms['plain']:.1f} ms per iteration; "
                     f"frozen / plain {frozen_plain:.2f}, unfrozen / plain {unfrozen_plain:.2f}, "
                     f"frozen / unfrozen {frozen_unfrozen:.2f}; last losses frozen = unfrozen: "
                     f"{'yes' if same else 'no'}")
        print(f"bench: frozen {lines[-1][2:]}", file=sys.stderr, flush=True)


def _thesis(settings: Settings, server: common.Daemon, iterations: int, rounds: int,
            rows: list[dict], targets: list[Target], lines: list[str]) -> None:
    lines += ["", f"The thesis's Tables 2 and 4 from the thesis's starts, {iterations} "
              "iterations, the daemon's defaults at the plain loop's spp (Table 2: 16, Table 4: "
              "8) against bench/real_scenes.py's plain loop; the daemon's time from iteration "
              "0's end to the job's end (its differences, standard errors and result renders "
              "in), the plain loop's from iteration 0's end to its last; ms per iteration "
              "(median) and ratios per round (median). The parts of the defaults' time: "
              "their iterations alone (differences in), and the job's end: J (the standard "
              "errors, as the job's notes time them) and the rest (result images at 64 spp). "
              "Equal work: the plain loop's own steps (the plain preset) frozen, their "
              "iterations alone."]
    gpu = server.cuda and not settings.quick  # --quick: the CPU's cells, smaller
    tables = [t for t in real_scenes.TABLES if (not gpu or t.name in GPU_TABLES)
              and (not settings.tables or t.name in settings.tables)]
    sizes = [settings.film] if settings.film else GPU_SIZES if gpu else THESIS_SIZES
    for table in tables:
        for width, height in sizes:
            size = f"{width}x{height}"
            p = real_scenes.Plan((width, height), iterations, 1, False, server.cuda)
            prep = real_scenes.prepare(server.client, table, p, settings)
            parts: dict[str, list[float]] = {"iterations": [], "J": [], "end": [],
                                             "equal work": []}

            def job(method: str) -> Side:
                def side(r: int) -> tuple[float, float]:
                    # EQUAL_WORK: the plain preset (the plain loop's steps), frozen
                    frozen = "off" if method == "defaults, frozen off" else "on"
                    spec = real_scenes.daemon_spec(prep, 0, iterations, {"frozen": frozen},
                                                   preset_plain=method == EQUAL_WORK)
                    spec.spp = table.plain_spp
                    done = common.run_job(server.client, spec, server=server)
                    common.require_success(done, f"frozen {table.name}")
                    n = len(done.history) - 1
                    loop = done.seconds[-1] - done.seconds[0]
                    whole = ((done.wall - done.first_iteration) / n
                             if done.first_iteration is not None else float("nan"))
                    if method == "defaults" and r >= 0:
                        parts["iterations"].append(loop / n)
                        parts["end"].append(whole * n - loop)
                        parts["J"].append(_j_seconds(done.job.notes))
                    if method == EQUAL_WORK and r >= 0:
                        parts["equal work"].append(loop / n)
                    return _row(rows, table.name, size, method, r, whole,
                                done.history[-1].loss)
                return side

            def loop(r: int) -> tuple[float, float]:
                run = real_scenes.run_plain(prep, p, 0, server.variant, iterations)
                return _row(rows, table.name, size, "plain", r, run.per_iteration, float("nan"))

            times, _ = _rounds({m: job(m) for m in ("defaults", "defaults, frozen off",
                                                    EQUAL_WORK)} | {"plain": loop}, rounds)
            ratio = _ratio(times, "defaults", "plain")
            off = _ratio(times, "defaults, frozen off", "plain")
            alone = common.median([a / b for a, b in zip(parts["iterations"], times["plain"])])
            equal = common.median([a / b for a, b in zip(parts["equal work"], times["plain"])])
            target = TARGETS.get(width)
            targets.append(Target(
                f"{table.name} {size}: defaults / plain loop"
                + (f" (<= {target}, CPU)" if target else ""),
                f"{ratio:.2f} (their iterations alone {alone:.2f}; frozen off: {off:.2f}; the "
                f"plain loop's steps frozen, iterations alone: {equal:.2f})",
                None if target is None else ratio <= target))
            ms = {m: common.median(t) * 1000 for m, t in times.items()}
            end, j = common.median(parts["end"]), common.median(parts["J"])
            lines.append(f"- {table.name} {size}: defaults {ms['defaults']:.0f} ms, frozen off "
                         f"{ms['defaults, frozen off']:.0f} ms, plain loop {ms['plain']:.0f} ms "
                         f"per iteration; defaults / plain {ratio:.2f}, frozen off / plain "
                         f"{off:.2f}; the defaults' iterations alone "
                         f"{common.median(parts['iterations']) * 1000:.0f} ms ({alone:.2f} of "
                         f"the plain loop's), their end {end:.2f} s (J {j:.2g} s, the result "
                         f"renders and the rest {end - j:.2f} s); the plain loop's own steps "
                         f"frozen (equal work), their iterations alone "
                         f"{common.median(parts['equal work']) * 1000:.0f} ms ({equal:.2f})")
            print(f"bench: frozen {lines[-1][2:]}", file=sys.stderr, flush=True)


_J = re.compile(r"standard errors: \d+ components, ([0-9.e+-]+) s")


def _j_seconds(notes) -> float:
    """J's seconds, as the job's notes give them (two significant digits); 0 when none."""
    for note in notes:
        m = _J.search(note)
        if m:
            return float(m.group(1))
    return 0.0


def _row(rows: list[dict], scene: str, size: str, method: str, r: int, seconds: float,
         loss: float) -> tuple[float, float]:
    rows.append({"scene": scene, "size": size, "round": r, "method": method,
                 "seconds_per_iteration": seconds, "loss_last": loss})
    return seconds, loss


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    iterations, rounds = (20, 3) if settings.quick else (50, 3)
    rows: list[dict] = []
    targets: list[Target] = []
    lines: list[str] = []
    if server.cuda and not settings.quick:
        # A GPU loan's share holds the thesis's cell alone; overhead times the Cornell box there.
        lines.append("The Cornell box: not run on a GPU (bench/overhead.py times it there).")
    else:
        _cornell(settings, server, iterations, rounds, rows, targets, lines)
    repo = settings.thesis_repo
    if repo is not None and (repo / real_scenes.TABLES[0].path).exists():
        # The thesis's 100 iterations weigh the job's end as its jobs do.
        count, rounds = ((15, rounds) if settings.quick else (GPU_ITERATIONS, GPU_ROUNDS)
                         if server.cuda else (100, rounds))
        _thesis(settings, server, count, rounds, rows, targets, lines)
    else:
        lines += ["", f"The thesis's Tables 2 and 4: skipped ({repo} has no thesis scenes)."]
    csv = common.write_csv(settings.out / "frozen.csv", rows)
    return Result("frozen", "Frozen iterations against unfrozen and a plain loop", targets,
                  lines, [csv], time.perf_counter() - began)
