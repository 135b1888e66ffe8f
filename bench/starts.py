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


def _thesis(settings: Settings, server: common.Daemon, rows: list[dict]) -> None:
    for plan in (p for p in tt.plans(quick=True) if p.case in TABLES):
        for n in STARTS:
            _, runs, _ = tt.measure(dataclasses.replace(plan, starts=n, plain=False,
                                                        seeds=SEEDS), settings, server)
            for run in runs:
                several = _several(run.reasons, run.notes)
                rows += [{"suite": "thesis", "case": plan.case, "parameter": key, "starts": n,
                          "seed": run.seed, "error": error, "seconds": run.seconds,
                          "iterations": run.iterations, "several": key in several}
                         for key, error in run.errors.items()]


def _stiff(server: common.Daemon, rows: list[dict]) -> None:
    client = server.client
    for case in stiff.CASES:
        for n in STARTS:
            for seed in range(SEEDS):
                out = stiff.run(client, dataclasses.replace(
                    case, spec={**case.spec, "starts": n, "seed": seed}))
                best = client.jobs.GetJobResult(pb.GetJobResultRequest(name=out.job.name))
                several = _several({v.key: list(v.interval_reason) for v in best.parameters},
                                   out.job.notes)
                rows += [{"suite": "stiff", "case": case.name, "parameter": key, "starts": n,
                          "seed": seed, "error": out.errors.get(key, float("nan")),
                          "seconds": out.job.elapsed_seconds, "iterations": out.job.iteration,
                          "several": key in several} for key in case.start]


def _line(group: list[dict]) -> str:
    """One case and parameter: error and time per N over the seeds, several answers said."""
    cells = []
    for n in STARTS:
        mine = [r for r in group if r["starts"] == n]
        errors = ", ".join(f"{r['error']:.3g}" for r in mine)
        seconds = float(np.mean([r["seconds"] for r in mine])) if mine else float("nan")
        said = sum(r["several"] for r in mine)
        cells += [errors, f"{seconds:.1f}", f"{said} of {len(mine)}"]
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
    better = sum(np.mean([r["error"] for r in rows if (r["suite"], r["case"], r["parameter"])
                         == k and r["starts"] == 3])
                 < 0.9 * np.mean([r["error"] for r in rows if (r["suite"], r["case"],
                                  r["parameter"]) == k and r["starts"] == 1]) for k in keys)
    return Result("starts", "Starts compared (--starts 3 against 1)", [
        Target("optimizing time, 3 starts over 1 (mean over the jobs)",
               f"{cost[1] / cost[0]:.2f}x", True),
        Target("parameters whose mean error fell by more than 10% with 3 starts",
               f"{better} of {len(keys)}", True),
    ], [
        "Each job as its suite runs it (bench/thesis_tables.py at its quick sizes without the "
        "plain loop; tests/stiff.py), with --starts 1 and 3, seeds 0 and 1. Error: relative, "
        "as the case judges it; time: the job's optimizing seconds, probes included; several: "
        "jobs whose result says the images allow several answers for the parameter.",
        "",
        "| suite | case | parameter | error, 1 start | s | several | error, 3 starts | s "
        "| several |",
        "|---|---|---|---|---|---|---|---|---|",
        *table,
    ], [csv], time.perf_counter() - began)
