"""Starts compared (JobSettings.starts): what three starts cost and buy against one, on the
thesis's Table 3 and Table 5 analogues (tests/thesis_scenes.py, at bench/thesis_tables.py's
quick sizes) and on the stiff cases (tests/stiff.py), two seeds each.

Per case, parameter, N and seed: the relative error at the end (as the cases judge it), the
job's optimizing time (probes included) and whether its result says that the images allow
several answers. N = 3 runs three probes of max(10, iterations / 12) iterations, then the
rest of the job from the best one: it costs about two probes' iterations more.
"""

from __future__ import annotations

import dataclasses
import re
import time

import numpy as np

import common
import stiff
import thesis_tables as tt
from common import Result, Settings, Target
from matopt_api.v1 import matopt_pb2 as pb

STARTS = (1, 3)
SEEDS = 2
SEVERAL = "the images allow several answers"
TABLES = ("table3", "table5")


def _several(reasons: dict[str, list[str]], notes) -> list[str]:
    """The parameters a result says have several answers (a texture's by its note)."""
    keys = [k for k, rs in reasons.items() if any(r.startswith(SEVERAL) for r in rs)]
    return keys + [n.split(":")[0] for n in notes if SEVERAL in n and not n.startswith("probe")]


PROBE = re.compile(r"probe (\d+) of \d+: .*, (\d+) iterations to ")
WENT_ON = re.compile(r"goes on from probe (\d+) ")


def _probes(notes, iterations: int) -> tuple[int, int]:
    """The probe the job went on from (0: none ran) and the iterations it rendered in all:
    its own, and those of the probes it did not go on from."""
    ran = {int(m[1]): int(m[2]) for n in notes if (m := PROBE.match(n))}
    went = next((int(m[1]) for n in notes if (m := WENT_ON.search(n))), 0)
    return went, iterations + sum(ran.values()) - ran.get(went, 0)


def _row(suite: str, case: str, key: str, n: int, seed: int, error: float, seconds: float,
         iterations: int, notes, several: list[str]) -> dict:
    went, rendered = _probes(notes, iterations)
    return {"suite": suite, "case": case, "parameter": key, "starts": n, "seed": seed,
            "error": error, "seconds": seconds, "iterations": rendered, "went_on_from": went,
            "several": key in several,
            "probes": " | ".join(n for n in notes if PROBE.match(n) or SEVERAL in n)}


def _thesis(settings: Settings, server: common.Daemon, rows: list[dict]) -> None:
    for plan in (p for p in tt.plans(quick=True) if p.case in TABLES):
        # a first job compiles the case's kernels, which the others then find cached
        tt.measure(dataclasses.replace(plan, plain=False, seeds=1), settings, server)
        for n in STARTS:
            _, runs, _ = tt.measure(dataclasses.replace(plan, starts=n, plain=False,
                                                        seeds=SEEDS), settings, server)
            for run in runs:
                several = _several(run.reasons, run.notes)
                rows += [_row("thesis", plan.case, key, n, run.seed, error, run.seconds,
                              run.iterations, run.notes, several)
                         for key, error in run.errors.items()]


def _stiff(server: common.Daemon, rows: list[dict]) -> None:
    client = server.client
    for case in stiff.CASES:
        stiff.run(client, case)  # compiles the case's kernels (not counted)
        for seed in range(SEEDS):
            for n in STARTS if seed % 2 == 0 else STARTS[::-1]:
                out = stiff.run(client, dataclasses.replace(
                    case, spec={**case.spec, "starts": n, "seed": seed}))
                best = client.jobs.GetJobResult(pb.GetJobResultRequest(name=out.job.name))
                several = _several({v.key: list(v.interval_reason) for v in best.parameters},
                                   out.job.notes)
                rows += [_row("stiff", case.name, key, n, seed,
                              out.errors.get(key, float("nan")), out.job.elapsed_seconds,
                              out.job.iteration, out.job.notes, several) for key in case.start]


def _line(group: list[dict]) -> str:
    """One case and parameter: per N over the seeds, the errors, the mean time and
    iterations rendered, the probe gone on from, and how many results said several answers."""
    cells = []
    for n in STARTS:
        mine = sorted((r for r in group if r["starts"] == n), key=lambda r: r["seed"])
        cells += [", ".join(f"{r['error']:.3g}" for r in mine),
                  f"{np.mean([r['seconds'] for r in mine]):.1f}",
                  f"{np.mean([r['iterations'] for r in mine]):.0f}"]
        if n > 1:
            cells.append(", ".join(str(r["went_on_from"] or "-") for r in mine))
        cells.append(f"{sum(r['several'] for r in mine)} of {len(mine)}")
    r = group[0]
    return f"| {r['suite']} | {r['case']} | {r['parameter'].split('.')[-2]} | " + \
        " | ".join(cells) + " |"


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    rows: list[dict] = []
    _thesis(settings, server, rows)
    _stiff(server, rows)
    csv = common.write_csv(settings.out / "starts.csv", rows)
    keys = list(dict.fromkeys((r["suite"], r["case"], r["parameter"]) for r in rows))
    table = [_line([r for r in rows if (r["suite"], r["case"], r["parameter"]) == k])
             for k in keys]
    cost = [np.mean([r["seconds"] for r in rows if r["starts"] == n]) for n in STARTS]
    rendered = [np.mean([r["iterations"] for r in rows if r["starts"] == n]) for n in STARTS]
    better = sum(np.mean([r["error"] for r in rows if (r["suite"], r["case"], r["parameter"])
                         == k and r["starts"] == 3])
                 < 0.9 * np.mean([r["error"] for r in rows if (r["suite"], r["case"],
                                  r["parameter"]) == k and r["starts"] == 1]) for k in keys)
    return Result("starts", "Starts compared (--starts 3 against 1)", [
        Target("optimizing time, 3 starts over 1 (mean over the jobs)",
               f"{cost[1] / cost[0]:.2f}x", True),
        Target("iterations rendered, 3 starts over 1 (mean over the jobs)",
               f"{rendered[1] / rendered[0]:.2f}x", True),
        Target("parameters whose mean error fell by more than 10% with 3 starts",
               f"{better} of {len(keys)}", True),
    ], [
        "Each job as its suite runs it (bench/thesis_tables.py at its quick sizes without the "
        "plain loop; tests/stiff.py), with --starts 1 and 3, seeds 0 and 1. Error: relative, "
        "as the case judges it; time: the job's optimizing seconds, probes included; several: "
        "jobs whose result says the images allow several answers for the parameter; "
        "iterations: those rendered, the probes' included; went on from: the probe the job "
        "continued (1: the given start; -: no probes, as where no parameter has a finite "
        "range). Each case's first job, which compiles its kernels, is not counted; the "
        "stiff cases alternate which N runs first.",
        "",
        "| suite | case | parameter | error, 1 start | s | iterations | several | error, 3 "
        "starts | s | iterations | went on from probe | several |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
        *table,
    ], [csv], time.perf_counter() - began)
