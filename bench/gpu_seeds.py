"""real_scenes' GPU seeds, added up across device loans.

A loan of 15 minutes fits one seed of Table 4 at 683x512 (about 380 s with a cold kernel
cache), so a median over 3 seeds takes runs on several loans.
``python bench/run.py --splice DIR --add-seeds`` adds the seeds of DIR's real_scenes run to
those bench/results/gpu/ holds for the same tables: a seed run again replaces its rows. It
writes one CSV per table, each row naming the run it comes from, and rewrites those tables'
blocks and figures in the GPU section; every other case and table stays as it was. Add only
seeds run on the same defaults: each table's block names every seed's run and commit.
"""

from __future__ import annotations

import csv
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import common
import gpu_run
import real_scenes as rs

CASE = "real_scenes"
ORDER = {"plain": 0, "daemon": 1, rs.EQUAL_TIME: 2}  # each seed's rows, as the runs ran them
MARK = {True: "met", False: "MISSED", None: "n/a"}
PLAN = rs.Plan((683, 512), 0, 0, False, True)  # what the report and targets read of it: a GPU's


@dataclass
class KeptRun:
    """A run as its CSV row keeps it: what real_scenes' report and targets read of a Run."""
    table: str
    method: str
    seed: int
    per_iteration: float
    cpu_per_iteration: float
    final: dict[str, float]
    to: dict[float, float | None]  # seconds to 2% and 1% staying (None: never)
    run: str                       # when and on which commit it ran
    values: dict[str, str] = field(default_factory=dict)  # the CSV's end values, as written
    integrator: str = ""
    choices: list = field(default_factory=list)

    def staying(self, keys, threshold: float) -> float | None:
        return self.to[threshold]


def kept_run(row: dict[str, str], table: rs.Table, run: str) -> KeptRun:
    keys = {rs._short(k): k for k in table.truth}

    def seconds(text: str) -> float | None:
        return float(text) if text else None

    return KeptRun(table.name, row["method"], int(row["seed"]),
                   float(row["seconds_per_iteration"]), float(row["cpu_per_iteration"]),
                   {keys[k[6:]]: float(v) for k, v in row.items() if k.startswith("final:")},
                   {0.02: seconds(row["to_2pct"]), 0.01: seconds(row["to_1pct"])},
                   row.get("run") or run, {k: v for k, v in row.items() if k.startswith("value:")})


def run_of(summary: str) -> str:
    """"DATE TIME UTC, commit C" from a --gpu run's summary.md."""
    when = re.search(r"\((?:finished|in progress: partial)\): (\d{4}-\d\d-\d\d \d\d:\d\d UTC)",
                     summary)
    commit = re.search(r"commit (\w+)", summary)
    if not when or not commit:
        raise SystemExit("summary.md: no run's date and commit in its head line")
    return f"{when.group(1)}, {commit.group(1)}"


def read(folder: Path, run: str = "") -> dict[str, list[KeptRun]]:
    """The runs of each table in ``folder``'s real_scenes CSVs (``run`` where a row names
    none)."""
    tables = {t.name: t for t in rs.TABLES}
    out: dict[str, list[KeptRun]] = {}
    for path in sorted((folder / "cases" / CASE).glob("real_scenes*.csv")):
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                out.setdefault(row["table"], []).append(kept_run(row, tables[row["table"]], run))
    return out


def combined(before: list[KeptRun], after: list[KeptRun]) -> list[KeptRun]:
    """``after`` with the seeds of ``before`` it did not run, in seed order."""
    seeds = {r.seed for r in after}
    runs = [r for r in before if r.seed not in seeds] + after
    return sorted(runs, key=lambda r: (r.seed, ORDER.get(r.method, len(ORDER)), r.method))


def provenance(runs: list[KeptRun]) -> str:
    """"seeds 0 and 1 on RUN; seed 2 on RUN" for the daemon's seeds."""
    by_run: dict[str, list[int]] = {}
    for r in runs:
        if r.method == "daemon":
            by_run.setdefault(r.run, []).append(r.seed)
    return "; ".join(f"seed{'s' if len(s) > 1 else ''} "
                     f"{' and '.join(', '.join(map(str, s)).rsplit(', ', 1))} on {run}"
                     for run, s in by_run.items())


def blocks(subsection: str) -> tuple[list[str], dict[str, list[str]]]:
    """real_scenes' subsection as its lines before the first table and each table's block by
    name (its "Data:" line, rewritten from the files, dropped)."""
    head: list[str] = []
    tables: dict[str, list[str]] = {}
    current = None
    for line in subsection.splitlines():
        m = re.match(r"\*\*(table\d+)\*\*", line)
        if m:
            current = m.group(1)
            tables[current] = []
        if line.startswith("Data: "):
            break
        (tables[current] if current else head).append(line)
    return head, tables


def table_block(table: rs.Table, runs: list[KeptRun], new: list[str]) -> list[str]:
    """The table's block over ``runs``: the new run's first line (the scene, the integrator,
    the plain loop's settings) with where each seed comes from, and its choices' lines."""
    first = re.sub(r"; \d+ s\)$", ")", new[0])  # the run's seconds: not the seeds'
    lines = rs.table_lines(table, PLAN, runs)  # type: ignore[arg-type]
    choices = next((i for i, ln in enumerate(new) if ln.startswith("The job's integrator")),
                   len(new))
    # "Per seed:", a blank line, the head and its rule, a row per run
    body = lines[:lines.index("Per seed:") + 4 + len(runs)]
    return [f"{first}: {provenance(runs)}; the choices' lines are the newest run's.", "",
            *body, "", *new[choices:]]


def target_rows(table: rs.Table, runs: list[KeptRun]) -> list[str]:
    seeds = sorted({r.seed for r in runs if r.method == "daemon"})
    out = [f"| {CASE} | {t.what} | {gpu_run._cell(t.figure)} | {MARK[t.met]} |"
           for t in rs.targets(table, PLAN, runs)]  # type: ignore[arg-type]
    return out + [f"| {CASE} | {table.name}: seeds | {len(seeds)} ({', '.join(map(str, seeds))}),"
                  f" {provenance(runs)} | n/a |"]


def _about(row: str, table: str) -> bool:
    """A section's row of real_scenes about ``table``."""
    cells = [c.strip() for c in row.split("|")]
    return cells[1] == CASE and re.match(rf"(GPU )?{table}\b", cells[2]) is not None


def add(source: Path, docs: Path, results: Path = gpu_run.RESULTS) -> int:
    """``source``'s real_scenes seeds added to ``results``' and to ``docs``' GPU section."""
    summary = (source / "summary.md").read_text()
    new = read(source, run_of(summary))
    if not new:
        raise SystemExit(f"{source}: no real_scenes CSV under cases/{CASE}/")
    ran = gpu_run._split(summary)[2].get(CASE)
    if ran is None:
        raise SystemExit(f"{source / 'summary.md'}: no real_scenes section to add seeds from")
    new_top, new_blocks = blocks(ran)
    if missing := sorted(new.keys() - new_blocks.keys()):
        raise SystemExit(f"{source / 'summary.md'}: rows of {', '.join(missing)} in its CSVs "
                         "but no block of them in its section (a run stopped before its report?)")
    page = docs.read_text()
    section = gpu_run.current(page)
    if not section:
        raise SystemExit(f"{docs}: no GPU section to add seeds to (splice a run without "
                         "--add-seeds first)")
    head_lines, rows, subs = gpu_run._split(section)
    before = read(results, "an earlier run")
    top, old_blocks = blocks(subs[CASE]) if CASE in subs else (new_top, {})
    folder = results / "cases" / CASE
    folder.mkdir(parents=True, exist_ok=True)
    tables = {t.name: t for t in rs.TABLES}
    for name in before.keys() - new.keys():
        write(folder / f"real_scenes-{name}.csv", before[name])
    for name, runs in new.items():
        runs = combined(before.get(name, []), runs)
        old_blocks[name] = table_block(tables[name], runs, new_blocks[name])
        at = next((i for i, r in enumerate(rows) if _about(r, name)), len(rows))
        rows = [r for r in rows if not _about(r, name)]
        rows[at:at] = target_rows(tables[name], runs)
        write(folder / f"real_scenes-{name}.csv", runs)
    for stale in folder.glob("real_scenes*.csv"):  # a table's rows live in its own file now
        if not re.fullmatch(r"real_scenes-table\d+\.csv", stale.name):
            stale.unlink()
    files = sorted(folder.glob("real_scenes-*.csv"))
    data = "Data: " + ", ".join(f"[cases/{CASE}/{f.name}]({gpu_run.LINK}cases/{CASE}/{f.name})"
                                for f in files)
    lines = [*top]
    for name in old_blocks:  # the tables in the order the section had them, new ones last
        lines += [*old_blocks[name]]
        if lines[-1].strip():
            lines.append("")
    subs[CASE] = "\n".join([*lines, data])
    while head_lines and not head_lines[-1].strip():
        head_lines.pop()
    block = "\n".join([gpu_run.BEGIN, *head_lines, "", "| case | figure | result | met |",
                       "|---|---|---|---|", *rows, *[x for s in subs.values() for x in ("", s)],
                       gpu_run.END]) + "\n"
    (results / "summary.md").write_text(block)
    docs.write_text(gpu_run.keep_section(page, block))
    added = ", ".join(f"{n} seeds {sorted({r.seed for r in v})}" for n, v in new.items())
    print(f"bench: added {added} to the GPU section of {docs}; its head line is as it was",
          file=sys.stderr)
    return 0


def write(path: Path, runs: list[KeptRun]) -> None:
    rows = [{"table": r.table, "method": r.method, "seed": r.seed,
             "seconds_per_iteration": r.per_iteration, "cpu_per_iteration": r.cpu_per_iteration,
             "to_2pct": r.to[0.02], "to_1pct": r.to[0.01],
             **{f"final:{rs._short(k)}": v for k, v in r.final.items()}, **r.values,
             "run": r.run} for r in runs]
    common.write_csv(path, rows)
