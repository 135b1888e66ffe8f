"""Stability on stiff and extreme cases: every case of tests/stiff.py (near-specular, eta near
1 and at 2.5, optically thin and thick media, albedo 0.999 coupled to sigma_t, radiance 1e3
next to a reflectance of 0.5, HDR and very dark references) plus the guards' own cases (an
all-black reference, learning rates of 1e-5 and 1), each rendered from known values and
optimized by the daemon with its defaults unless the case says otherwise. With
``--with-choice NAME=VALUE`` each case runs again with that choice set (``--candidate-only``: only
so): a candidate default must keep every promise here as well as win the matrix's cells
(bench/defaults_matrix.py). References with
NaN/Inf pixels and 1 spp with the dual-buffer loss are tests only (tests/test_api.py,
tests/test_stability.py): they assert how the loss treats them, which a table would not add to.

Reported per case: the relative error of each parameter (of alpha for a principled roughness),
the smallest value each took (a dielectric's eta must stay above 1), whether any value was
NaN/Inf or left its range, the guards that fired (NaN gradient steps, skipped steps, clamped
components), the job's diagnosis notes, and whether the case's promise held (its tolerance,
or the diagnosis it must give). The test suite runs the same cases (tests/test_stability.py);
here they are tabulated with times.
"""

from __future__ import annotations

import dataclasses
import time

import common
import numpy as np
import stiff
from common import Result, Settings, Target
from stiff import Case, glass, sky

RED = "red.reflectance.value"


def _guard_cases() -> list[Case]:
    """The guards' cases, as stiff cases: they have no tolerance, only validity and notes."""
    ball = "ball.bsdf.alpha.value"
    out = [Case(f"learning rate {lr:g}", glass(1.5), {ball: [0.5]}, {ball: [0.2]}, 20,
                rates={ball: lr}, why="the extremes of the learning rate",
                expect_note=stiff.LOSS_DID_NOT_FALL if lr < 1e-3 else ())
           for lr in (1e-5, 1.0)]
    out.append(Case("all-black reference", sky(0.0), {"emitter_0.radiance.value": [1.0] * 3},
                    {"emitter_0.radiance.value": [0.0] * 3}, 60,
                    within={"emitter_0.radiance.value": (0.0, 0.1)},
                    rates={"emitter_0.radiance.value": 0.2}, reference_spp=1,
                    why="black is the infimum of a non-negative radiance: log space must "
                        "approach it without reaching log(0)"))
    return out


def _short(key: str) -> str:
    return ".".join(p for p in key.split(".") if p != "value")


def _values(v) -> str:
    v = np.ravel(v)
    same = np.allclose(v, v[0]) if v.size else True
    return f"{v[0]:.4g}" if same else ", ".join(f"{x:.4g}" for x in v)


def _notes(job) -> str:
    skip = ("gradients for:", "sensors rendered:")
    return "; ".join(n for n in job.notes if not n.startswith(skip)) or "-"


def _candidate(case: Case, choices: dict[str, str]) -> Case:
    """The case with ``choices`` (and JobSpec fields, ``common.candidate``) set over its own
    (a candidate default on trial)."""
    choices, fields = common.candidate(choices)
    spec = dict(case.spec, **fields, choices={**case.spec.get("choices", {}), **choices})
    return dataclasses.replace(case, name=f"{case.name}, candidate", spec=spec)


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    plain = [(c, False) for c in stiff.CASES + _guard_cases()]
    cases = plain  # (case, whether it runs the candidate)
    if settings.with_choices:
        trial = [(_candidate(c, settings.with_choices), True) for c, _ in plain]
        cases = trial if settings.candidate_only else [
            c for pair in zip(plain, trial) for c in pair]
    rows, table, held = [], [], {False: [0, 0], True: [0, 0]}  # candidate? -> [held, run]
    for case, candidate in cases:
        try:
            out = stiff.run(server.client, case)
            broken = stiff.verdict(case, out)
        except Exception as exc:  # noqa: BLE001 - a failed case is a row too
            broken, out = [f"{type(exc).__name__}: {exc}"], None
        held[candidate][0] += not broken
        held[candidate][1] += 1
        if out is None:
            table.append(f"| {case.name} | - | - | - | - | - | - | FAILED: {broken[0]} |")
            continue
        guards = (f"{out.job.nonfinite_gradient_steps} / {out.job.skipped_steps} / "
                  f"{out.job.clamped_components}")
        for key in case.start:
            error = out.errors.get(key, float("nan"))
            rows.append({"case": case.name, "parameter": key,
                         "truth": _values(case.truth[key]), "start": _values(case.start[key]),
                         "final": _values(out.final.get(key, [np.nan])),
                         "relative_error": error, "lowest": out.lowest[key],
                         "finite": out.finite, "in_range": out.in_range,
                         "nonfinite_steps": out.job.nonfinite_gradient_steps,
                         "skipped_steps": out.job.skipped_steps,
                         "clamped": out.job.clamped_components,
                         "held": not broken, "seconds": out.seconds})
            table.append(
                f"| {case.name} | {_short(key)} | {_values(case.truth[key])} / "
                f"{_values(case.start[key])} / {_values(out.final.get(key, [np.nan]))} | "
                f"{error:.3g} | {out.lowest[key]:.4g} | {'yes' if out.finite and out.in_range else 'NO'} | "
                f"{guards} | {'held' if not broken else 'BROKEN: ' + '; '.join(broken)} |")
        table.append(f"| | *{case.why}* | | | | | {out.seconds:.1f} s | {_notes(out.job)} |")
    csv = common.write_csv(settings.out / "stability.csv", rows)
    named = ", ".join(f"{k}={v}" for k, v in settings.with_choices.items())
    targets = [Target(f"cases whose promise held (tolerance, or the diagnosis they must give)"
                      + (f", the candidate {named}" if candidate else ""),
                      f"{n} of {total}", n == total)
               for candidate, (n, total) in held.items() if total]
    return Result("stability", "Stiff and extreme cases", targets, [
        "Each case: a small procedural scene (tests/stiff.py) rendered from the truth, the job "
        "started from the start value with the daemon's defaults (16 spp, cosine decay, "
        "the default learning rates unless the case sets one), min error 0. Error: relative "
        "RMSE against the truth (for a principled roughness, of alpha = max(0.001, r^2), the "
        "quantity the BSDF can show). Guards: steps with NaN/Inf gradient components "
        "zeroed / steps skipped for a NaN loss / components clamped into range.",
        "",
        "| case | parameter | truth / start / final | rel. error | lowest | finite, in range "
        "| guards | promise; notes |",
        "|---|---|---|---|---|---|---|---|",
        *table,
    ], [csv], time.perf_counter() - began)
