"""``python bench/run.py --gpu``: the figures owed on a GPU, within one device loan.

A lent GPU machine is held for minutes, so every case runs in a child process of its own
(``run.py --only CASE``) with a time cap: one slow case is stopped, reported as such, and
the rest still run. After each case the section so far is written to ``--out`` (summary.md,
with each case's CSVs under cases/), so that a loan that ends early still brings back what
finished. real_scenes, the largest figure owed, goes last: it runs a table's seeds while
the time for another fits in what is left, and says how many ran. ``python bench/run.py --splice DIR`` then copies DIR
to bench/results/gpu/ and puts its section into docs/benchmarks.md, between markers that a
full CPU run keeps.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import common
from common import Result, Target

# (case, cap in seconds, extra flags), in order; each cap is also held to what is left of the
# budget: 500 s of a device loan of 15 min, the rest for the machine's start and the unpacking
# (36 s and about 20 s on an H200, 2026-11-28). The short cases with targets go first;
# real_scenes, the largest figure, last: it runs a table's seeds while the time for another
# fits in what is left. frozen's cap holds its one GPU cell (bench/frozen.py) with a cold
# kernel cache.
PLAN: list[tuple[str, float, tuple[str, ...]]] = [
    ("demo", 35, ()),
    ("warm_start", 35, ()),
    ("overhead", 25, ()),
    ("calibration", 40, ("--cost-only",)),
    ("frozen", 180, ()),
    ("gpu_packing", 60, ()),
    ("real_scenes", 500, ("--defaults-only",)),
]
BUDGET = 500
GRACE = 45  # seconds past real_scenes' own deadline before it is stopped
BEGIN, END = "<!-- gpu-run -->", "<!-- /gpu-run -->"
RESULTS = common.ROOT / "bench" / "results" / "gpu"
LINK = "../bench/results/gpu/"  # RESULTS from docs/


def save_result(result: Result, info, path: Path) -> None:
    """A case's result as JSON, for the parent process (``--result-json``)."""
    data = dataclasses.asdict(result)
    data["files"] = [str(Path(f).resolve()) for f in result.files]
    data["info"] = ({"variant": info.variant, "device": info.device, "version": info.version}
                    if info else None)
    path.write_text(json.dumps(data))


def load_result(path: Path) -> tuple[Result, dict | None]:
    data = json.loads(path.read_text())
    info = data.pop("info")
    data["targets"] = [Target(**t) for t in data["targets"]]
    data["files"] = [Path(f) for f in data["files"]]
    return Result(**data), info


def card() -> str:
    """The GPU's name, memory and driver from nvidia-smi ("" without one)."""
    try:
        return subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total,driver_version",
                               "--format=csv,noheader"], capture_output=True, text=True,
                              timeout=30).stdout.strip().replace("\n", "; ")
    except (OSError, subprocess.SubprocessError):
        return ""


def child(name: str, extra: tuple[str, ...], args, out: Path, cap: float) -> Result:
    """One case in a child process of its own session, stopped (with its daemons) at ``cap``."""
    out.mkdir(parents=True, exist_ok=True)
    result_json = out / "result.json"
    command = [sys.executable, str(Path(__file__).with_name("run.py")), "--only", name,
               "--out", str(out), "--result-json", str(result_json), *extra]
    if args.quick:
        command.append("--quick")
    if args.variant:
        command += ["--variant", args.variant]
    if args.thesis_repo:
        command += ["--thesis-repo", str(args.thesis_repo)]
    if name == "real_scenes":
        command += ["--deadline", f"{time.time() + cap - GRACE:.0f}"]
        command += [*(["--seeds", str(args.seeds)] if args.seeds else []),
                    *(["--tables", *args.tables] if args.tables else []),
                    *(["--first-seed", str(args.first_seed)] if args.first_seed else []),
                    *(["--film", args.film] if args.film else []),
                    *(["--iterations", str(args.iterations)] if args.iterations else [])]
    began = time.perf_counter()
    with open(out / "log.txt", "wb") as log:
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                   start_new_session=True)
        try:
            process.wait(cap)
        except subprocess.TimeoutExpired:
            _stop(process)
    seconds = time.perf_counter() - began
    if process.returncode == 0 and result_json.exists():
        return load_result(result_json)[0]
    tail = (out / "log.txt").read_text(errors="replace").strip().splitlines()[-3:]
    why = (f"stopped at its cap of {cap:.0f} s" + (f"; its log's last: {tail[-1]}" if tail else "")
           if seconds >= cap else f"exited with status {process.returncode}: {' | '.join(tail)}")
    return Result(name, name, [Target("case ran", f"FAILED: {why}", False)], seconds=seconds)


def _stop(process: subprocess.Popen) -> None:
    """SIGTERM to the case's process group and every process below it (a private daemon of
    ``matopt demo`` runs in a session of its own), then SIGKILL to what is left."""
    below = _descendants(process.pid)
    for sig, wait in ((signal.SIGTERM, 20), (signal.SIGKILL, 10)):
        for pid in below:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)
        try:
            os.killpg(process.pid, sig)
            process.wait(wait)
            return
        except ProcessLookupError:
            return
        except subprocess.TimeoutExpired:
            continue


def _descendants(pid: int) -> list[int]:
    found, todo = [], [pid]
    while todo:
        for child in common.children(todo.pop()):
            found.append(child)
            todo.append(child)
    return found


def section(results: list[Result], out: Path, head: dict, done: bool) -> str:
    """The GPU section of docs/benchmarks.md, its links to where --splice copies ``out``."""
    when = head["when"]
    lines = [BEGIN, "## GPU run", "",
             f"`python bench/run.py --gpu{' --quick' if head['quick'] else ''}` "
             f"({'finished' if done else 'in progress: partial'}): {when}, "
             f"{head['minutes']:.1f} min of a {head['budget']:.0f} s budget"
             + (f", caps x{head['scale']:g}" if head["scale"] != 1 else "") + ". "
             f"Card: {head['card'] or 'none (nvidia-smi found none)'}; daemon: "
             f"{head['variant'] or '?'} on {head['device'] or '?'}; matopt "
             f"{head['version'] or '?'}, commit {common.git_revision()}. Each case ran in a "
             "process of its own with a time cap (bench/gpu_run.py); its CSVs are in "
             f"[bench/results/gpu/]({LINK}).", "",
             "| case | figure | result | met |", "|---|---|---|---|"]
    mark = {True: "met", False: "MISSED", None: "n/a"}
    for r in results:
        for t in r.targets:
            lines.append(f"| {r.name} | {t.what} | {_cell(t.figure)} | {mark[t.met]} |")
    for r in results:
        lines += ["", f"### {r.title} (`bench/{r.name}.py`, {r.seconds:.0f} s)", "", *r.lines]
        tables = [Path(f) for f in r.files if Path(f).suffix == ".csv"]
        if tables:
            rel = [Path(f).resolve().relative_to(out.resolve()).as_posix() for f in tables]
            lines += ["", "Data: " + ", ".join(f"[{p}]({LINK}{p})" for p in rel)]
    lines.append(END)
    return "\n".join(lines) + "\n"


def _cell(text: str) -> str:
    """``text`` on one line of a table row (an exception's message spans several)."""
    return " ".join(str(text).split()).replace("|", "\\|")


def run_all(args) -> int:
    """Every case of PLAN within ``args.budget`` seconds; summary.md after each."""
    out: Path = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    began = time.perf_counter()
    head = {"when": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "quick": args.quick, "budget": args.budget, "scale": args.cap_scale, "card": card(), "variant": "",
            "device": "", "version": "", "minutes": 0.0}
    results: list[Result] = []
    plan = [c for c in PLAN if not args.only or c[0] in args.only]
    for k, (name, cap, extra) in enumerate(plan):
        left = args.budget - (time.perf_counter() - began)
        cap = left if len(plan) == 1 else min(cap * args.cap_scale, left)  # alone: the budget
        if cap < 20:
            result = Result(name, name, [Target("case ran", "skipped: the budget was spent",
                                                None)])
        else:
            print(f"bench --gpu: {name} (cap {cap:.0f} s) ...", file=sys.stderr, flush=True)
            result = child(name, extra, args, out / "cases" / name, cap)
        results.append(result)
        for t in result.targets:
            print(f"  {t.what}: {t.figure}", file=sys.stderr, flush=True)
        info_file = out / "cases" / name / "result.json"
        if not head["variant"] and info_file.exists():
            info = load_result(info_file)[1]
            if info:
                head.update(info)
        head["minutes"] = (time.perf_counter() - began) / 60
        (out / "summary.md").write_text(section(results, out, head, k == len(plan) - 1))
    print(f"bench --gpu: wrote {out / 'summary.md'} ({head['minutes']:.1f} min)",
          file=sys.stderr)
    return 0


def splice(source: Path, docs: Path) -> int:
    """Copies a --gpu run's output to bench/results/gpu/ and its section into ``docs``. The
    cases it did not run (a loan's run of some cases, ``--only``) keep the figures and files
    of the section before, under a line saying which run they come from."""
    text = (source / "summary.md").read_text()
    if BEGIN not in text or END not in text:
        raise SystemExit(f"{source / 'summary.md'}: not the output of run.py --gpu")
    page = docs.read_text()
    block = merge(current(page), text)
    kept = _cases(current(page)) - _cases(text)
    if source.resolve() != RESULTS.resolve():
        for old in RESULTS.glob("cases/*"):
            if old.name not in kept:
                shutil.rmtree(old, ignore_errors=True)
        RESULTS.mkdir(parents=True, exist_ok=True)
        for f in source.rglob("*"):
            if f.is_file() and f.suffix in (".csv", ".md"):
                target = RESULTS / f.relative_to(source)
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(f, target)
    (RESULTS / "summary.md").write_text(block)
    docs.write_text(keep_section(page, block))
    print(f"bench: spliced the GPU section into {docs}", file=sys.stderr)
    return 0


def _cases(block: str) -> set[str]:
    """The cases a section holds, by its case headings."""
    return set(re.findall(r"^### .*\(`bench/(\w+)\.py`", block, re.M))


def _split(block: str) -> tuple[list[str], list[str], dict[str, str]]:
    """A section's head (its lines before the table), its table rows, and its case
    subsections by name."""
    body = block[block.index(BEGIN) + len(BEGIN):block.index(END)].strip("\n")
    top, _, rest = body.partition("\n### ")
    lines = top.splitlines()
    rows = [ln for ln in lines if ln.startswith("| ") and not ln.startswith("| case |")]
    head = [ln for ln in lines if not ln.startswith("|")]
    subsections = {}
    for part in ("### " + rest).split("\n### ") if rest else []:
        part = part if part.startswith("### ") else "### " + part
        m = re.match(r"### .*\(`bench/(\w+)\.py`", part)
        if m:
            subsections[m.group(1)] = part.rstrip("\n")
    return head, rows, subsections


def _own(head: list[str]) -> str:
    """A section's line about its own run (as written, or as rewritten by hand)."""
    return " ".join(ln for ln in head if ln.strip() and not ln.startswith(("#", "Earlier, for ")))


def merge(before: str, after: str) -> str:
    """``after``'s section, with the cases only ``before`` has appended as they were, each
    run they come from named in an "Earlier, for CASES: ..." line."""
    if not before:
        return after
    head_b, rows_b, subs_b = _split(before)
    head_a, rows_a, subs_a = _split(after)
    kept = [name for name in subs_b if name not in subs_a]
    if not kept:
        return after
    runs = []  # (cases, the run's line), the runs before ``after``
    for line in head_b:
        m = re.match(r"Earlier, for ([\w, ]+): (.*)", line)
        if m:
            runs.append((m.group(1).split(", "), m.group(2)))
    older = {c for cases, _ in runs for c in cases}
    runs.insert(0, ([c for c in subs_b if c not in older], _own(head_b)))
    notes = [f"Earlier, for {', '.join(left)}: {line}" for cases, line in runs
             if (left := [c for c in cases if c in kept])]
    rows = rows_a + [r for r in rows_b if r.split("|")[1].strip() in kept]
    lines = [BEGIN, "## GPU run", "", _own(head_a),
             *[x for note in notes for x in ("", note)], "",
             "| case | figure | result | met |", "|---|---|---|---|", *rows]
    for name, part in list(subs_a.items()) + [(n, subs_b[n]) for n in kept]:
        lines += ["", part]
    return "\n".join(lines) + "\n" + END + "\n"


def keep_section(page: str, block: str | None = None) -> str:
    """``page`` with its GPU section replaced by ``block`` (or appended); with ``block``
    None, the section already in ``page``, for a rewrite of the page to keep."""
    if BEGIN in page and END in page:
        start, stop = page.index(BEGIN), page.index(END) + len(END)
        return page[:start] + (block or "").rstrip("\n") + page[stop:]
    return page.rstrip("\n") + "\n\n" + block if block else page


def current(page: str) -> str:
    """The GPU section of ``page`` ("" when it has none)."""
    if BEGIN in page and END in page:
        return page[page.index(BEGIN):page.index(END) + len(END)] + "\n"
    return ""
