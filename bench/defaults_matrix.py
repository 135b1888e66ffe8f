"""The daemon's defaults judged on a matrix of configurations, not on one.

A default tuned where it was measured can cost elsewhere: on Table 4 at max_depth 64 the hold of
eta paid, at depth 8 it cost a factor of three. Each cell here is one of the thesis's tables on
its own scene (bench/real_scenes.py: its starts, truth, gated parameters and plain loop) at a
max_depth (the scene file's own and DEPTHS, set on the scene) and an spp (SPPS), 128x96 on
the CPU. In a cell both
sides render that spp and depth: the reference is rendered at the truth with the scene's
integrator at that depth, the daemon's job loads the scene with it (its ``depth`` choice may
still cut an unbounded one, as everywhere) and the plain loop loads the same scene file. Per
seed: the plain loop for the iterations, the daemon's defaults, and the plain loop again for
as long as the daemon's job took (equal time, which counts the daemon's extra renders against
it). Both draw the same samples per iteration (plain.DAEMON_SEED_STRIDE).

Per cell, the median over seeds of the worst final relative error of the table's gated
parameters and of the time to 2% and 1% staying (every gated parameter within it to the end).
Target per cell: the defaults' worst final error at most the plain loop's at equal time, and
their time to 2% staying at most half the plain loop's where that gets there. A second target
is the parameters' own: in every cell the defaults hold the gated parameters within the
table's ``gate`` (Table 2: 1%, Table 4: 2%) and staying within the job (median seed).

The whole matrix (Table 2 x 3 depths + Table 4 x 2 depths, x 3 spp x 3 seeds) is hours on
2 cores; the case runs the corner spp {8, 16} x 2 seeds unless ``--seeds``, ``--spp`` and
``--depth`` say otherwise; ``--quick``: one cell per table at 64x48, 20 iterations, one seed. ``--with-choice NAME=VALUE``
adds a candidate default per seed (the defaults with that choice set) beside them: a choice is
judged by the cells, not by the configuration it was tuned on. With ``--candidate-only`` the
candidate takes the defaults' place and is judged as they are (the plain loop at equal time
runs for its time), at two thirds of the cost. With ``--paths`` every run's values at every
iteration go to defaults_matrix-paths.jsonl, so that an estimate made from a job's path (an
average of its end, say) is judged on the very runs, not on new draws.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import common
import real_scenes as rs
from common import Result, Settings, Target

DAEMON = rs.DAEMON      # its references: 1024 spp in one call
DEPTHS = (8, 64)         # beside each scene file's own (Table 2 unbounded, Table 4 64)
SPPS = (8, 16, 32)
CORNER_SPPS, CORNER_SEEDS = (8, 16), 2
CANDIDATE = "candidate"  # the daemon with ``--with-choice`` set: a default on trial


@dataclasses.dataclass
class Cell:
    table: str
    depth: int
    spp: int
    runs: list[rs.Run]

    def of(self, method: str) -> list[rs.Run]:
        return [r for r in self.runs if r.method == method]


def cells(settings: Settings) -> list[tuple[rs.Table, int, int]]:
    """(table, depth, spp) of every cell run, in order."""
    tables = [t for t in rs.TABLES if not settings.tables or t.name in settings.tables]
    if settings.quick:
        return [(t, DEPTHS[-1], t.plain_spp) for t in tables]
    spps = settings.spps or CORNER_SPPS

    def depths(t: rs.Table) -> tuple[int, ...]:
        return settings.depths or tuple(dict.fromkeys((t.depth, *DEPTHS)))
    return [(t, d, s) for t in tables for d in depths(t) for s in spps]


def scene_overrides(depth: int) -> dict[str, str]:
    """An unbounded depth is the scene file as a user loads it: the daemon's ``depth`` choice
    measures and cuts it. A depth set on the scene is the user's, which that choice leaves
    as it stands, so -1 set explicitly would test a configuration no user gets by default."""
    return {} if depth < 0 else {"max_depth": str(depth)}


def measure(server: common.Daemon, settings: Settings, table: rs.Table, depth: int, spp: int,
            p: rs.Plan, references: dict) -> Cell:
    """The cell's runs; ``references``: (table, depth) -> reference, rendered once for all spp."""
    table = dataclasses.replace(table, plain_spp=spp)
    prep = rs.prepare(server.client, table, p, settings, scene_overrides(depth),
                      references.get((table.name, depth)))
    references[table.name, depth] = (prep.ref_blob, prep.ref_path)
    rs.run_plain(prep, p, 99, server.variant, rs.WARM_UP)  # kernels compiled on both sides
    rs.run_daemon(server, prep, "warm-up", rs.daemon_spec(prep, 99, rs.WARM_UP))
    runs: list[rs.Run] = []
    only = settings.with_choices if settings.candidate_only else {}
    for seed in range(settings.first_seed, settings.first_seed + p.seeds):
        if only:  # the candidate as "daemon", and no plain run at equal iterations
            runs.append(rs.run_daemon(server, prep, "daemon",
                                      rs.daemon_spec(prep, seed, p.iterations, only)))
        else:
            sides = [lambda: rs.run_plain(prep, p, seed, server.variant, p.iterations),
                     lambda: rs.run_daemon(server, prep, "daemon",
                                           rs.daemon_spec(prep, seed, p.iterations))]
            for side in sides[seed % 2:] + sides[:seed % 2]:
                runs.append(side())
        job = runs[-1] if runs[-1].method == "daemon" else runs[-2]
        runs.append(rs.run_plain(prep, p, seed, server.variant, p.iterations,
                                 seconds=job.seconds[-1]))
        if settings.with_choices and not only:  # a candidate default beside the defaults
            runs.append(rs.run_daemon(server, prep, CANDIDATE, rs.daemon_spec(
                prep, seed, p.iterations, settings.with_choices)))
        print(f"bench: defaults_matrix {table.name} depth {depth} spp {spp} seed {seed}: "
              + ", ".join(f"{r.method} {_worst(table, r):.4f} ("
                          + " ".join(f"{k.split('.')[1]} {r.final[k]:.4f}" for k in table.targets)
                          + ")" for r in runs if r.seed == seed), flush=True)
    return Cell(table.name, depth, spp, runs)


def _worst_key(table: rs.Table, run: rs.Run) -> str:
    return max(table.targets, key=lambda k: run.final[k])


def _worst(table: rs.Table, run: rs.Run) -> float:
    return run.final[_worst_key(table, run)]


def _median_time(table: rs.Table, runs: list[rs.Run], threshold: float) -> float:
    return common.median([math.inf if (t := r.staying(table.targets, threshold)) is None
                          else t for r in runs])


def won(table: rs.Table, cell: Cell) -> int:
    """Seeds on which the defaults end with a worst error at most the plain loop's at equal
    time: both draw the same samples per iteration, so a seed pairs their samples. It does
    not pair their outcomes: rounding differs from run to run and the noisy steps carry it
    on (docs/concepts.md, "Seeds"), so each side's end is a draw. With the seeds' spread as
    wide as Table 4's (a factor of five), a median of three can fall either way."""
    equal = {r.seed: _worst(table, r) for r in cell.of(rs.EQUAL_TIME)}
    return sum(_worst(table, r) <= equal[r.seed] for r in cell.of("daemon") if r.seed in equal)


def judge(table: rs.Table, cell: Cell) -> tuple[str, bool, bool]:
    """The cell's row (markdown), whether its target against the plain loop is met, and
    whether the defaults hold the gated parameters within the table's gate (median seed)."""
    daemon, equal, plain = cell.of("daemon"), cell.of(rs.EQUAL_TIME), cell.of("plain")
    worst = {m: common.median([_worst(table, r) for r in rs_])
             for m, rs_ in (("daemon", daemon), ("equal", equal), ("plain", plain))}
    two = {m: _median_time(table, rs_, 0.02) for m, rs_ in (("daemon", daemon),
                                                            ("equal", equal))}
    one = {m: _median_time(table, rs_, 0.01) for m, rs_ in (("daemon", daemon),
                                                            ("equal", equal))}
    met = worst["daemon"] <= worst["equal"] and (
        math.isinf(two["equal"]) or two["daemon"] <= 0.5 * two["equal"])
    gated = {m: _median_time(table, rs_, table.gate) for m, rs_ in (("daemon", daemon),
                                                                   ("equal", equal))}
    held = math.isfinite(gated["daemon"])
    row = (f"| {table.name} | {cell.depth} | {cell.spp} | {len(daemon)} | "
           f"{worst['daemon']:.4f} | {worst['equal']:.4f} | {worst['plain']:.4f} | "
           f"{won(table, cell)} of {len(daemon)} | "
           f"{rs._t(two['daemon'])} / {rs._t(two['equal'])} | "
           f"{rs._t(one['daemon'])} / {rs._t(one['equal'])} | {'met' if met else 'MISSED'} | "
           f"{'met' if held else 'MISSED'} |")
    if candidate := cell.of(CANDIDATE):
        worst_c = common.median([_worst(table, r) for r in candidate])
        row += (f" {worst_c:.4f} | {rs._t(_median_time(table, candidate, 0.02))} | "
                f"{common.median([r.seconds[-1] for r in candidate]):.0f} / "
                f"{common.median([r.seconds[-1] for r in daemon]):.0f} |")
    return row, met, held


def path_rows(cell: Cell) -> list[dict]:
    """A line per run of the cell: where it was (table, depth, spp), which side and seed, and
    its values and seconds at every iteration (``--paths``)."""
    return [{"table": cell.table, "depth": cell.depth, "spp": cell.spp, "method": r.method,
             "seed": r.seed, "seconds": r.seconds, "values": r.paths} for r in cell.runs]


def write_paths(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(row) + "\n" for row in rows))


def read_paths(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line]


def run(settings: Settings, server: common.Daemon) -> Result:
    result = Result("defaults_matrix", "The defaults on a matrix of depths and spp")
    extra = settings.with_choices and not settings.candidate_only  # the candidate's columns
    if settings.thesis_repo is None:
        result.targets.append(rs.NO_REPO)
        return result
    began = time.perf_counter()
    p = rs.plan(dataclasses.replace(settings, seeds=settings.seeds or (
        1 if settings.quick else CORNER_SEEDS)), server.variant)
    p = dataclasses.replace(p, on_off=False)
    todo = cells(settings)
    rows, csv = [], []
    met_cells, held_cells, references = 0, 0, {}
    paths: list[dict] = []
    for table, depth, spp in todo:
        cell = measure(server, settings, table, depth, spp, p, references)
        row, met, held = judge(table, cell)
        rows.append(row)
        met_cells += met
        held_cells += held
        csv += [{"table": table.name, "depth": depth, "spp": spp, "method": r.method,
                 "seed": r.seed, "seconds_per_iteration": r.per_iteration,
                 "worst_final": _worst(table, r),
                 "worst_key": _worst_key(table, r),
                 "to_2pct": r.staying(table.targets, 0.02),
                 "to_1pct": r.staying(table.targets, 0.01)} for r in cell.runs]
        # Written after every cell: a run stopped part way keeps the cells it finished.
        common.write_csv(settings.out / "defaults_matrix.csv", csv)
        if settings.paths:
            paths += path_rows(cell)
            write_paths(settings.out / "defaults_matrix-paths.jsonl", paths)
    result.targets.append(Target(
        "cells where the defaults' worst final error <= the plain loop's at equal time and "
        "their time to 2% staying <= half the plain loop's (where it gets there)",
        f"{met_cells} of {len(todo)}", met_cells == len(todo)))
    gates = "; ".join(f"{t.name} {t.gate:.0%}" for t in rs.TABLES
                      if any(c[0] is t for c in todo))
    result.targets.append(Target(
        f"cells where the defaults hold the gated parameters within their table's gate ({gates}) "
        "and staying (median seed)", f"{held_cells} of {len(todo)}", held_cells == len(todo)))
    result.lines += [
        f"{server.variant}, film {p.film[0]}x{p.film[1]}, {p.iterations} iterations, "
        f"{p.seeds} seed(s) per cell; {time.perf_counter() - began:.0f} s. Worst: the median "
        "over seeds of the worst final relative error of the table's gated parameters; "
        "times: median seconds to 2% (1%) staying, daemon / plain at equal time; seeds won: "
        "those on which the defaults end at most at the plain loop's worst at equal time.", "",
        "| table | max_depth | spp | seeds | worst, daemon | worst, plain at equal time | "
        "worst, plain at equal iterations | seeds won | to 2% (s) | to 1% (s) | target | "
        "gate |"
        + (" worst, candidate | candidate to 2% (s) | seconds, candidate / daemon |"
           if extra else ""),
        "|" + "---|" * (15 if extra else 12), *rows]
    named = ", ".join(f"`{k}={v}`" for k, v in settings.with_choices.items())
    if settings.candidate_only:
        result.lines.insert(1, f"The daemon's jobs: the defaults with {named}, in their place "
                            "(no plain run at equal iterations).")
    elif settings.with_choices:
        result.lines.insert(1, f"Candidate: the defaults with {named}.")
    result.files.append(common.write_csv(settings.out / "defaults_matrix.csv", csv))
    return result
