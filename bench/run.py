"""matopt's benchmarks: ``python bench/run.py [--quick] [--thesis-size] [--out bench/results]``.

Runs each case against a daemon of its own, started here (``python -m matoptd`` on a loopback
port, its variant as it picks it: CUDA when a GPU works, else LLVM on the CPU; the plain-
Mitsuba baselines use the same variant), so that no case inherits another's jobs, history or
worker state; a case module's ``DAEMON`` (keyword arguments of ``common.daemon``: users for a
tokens file, extra flags) says how its daemon starts, and a case that compares daemon
configurations starts those itself, and one with ``NEEDS_DAEMON = False`` (a simulation)
gets none (``server`` is None). Each case measures its own baseline in the same run,
alternating with it, and reports ratios. Writes CSVs, PNG plots and summary.md to --out; a
full run (not --quick, all cases) also copies the summary to docs/benchmarks.md, the results
page, whole; docs/benchmarks-history.md, kept by hand, holds earlier runs and is linked from it.

A case that fails is reported as failed in the summary (with the error); the others still run.
--quick is a smoke run of reduced cases (a few minutes on 2 CPU cores); the full run takes
about 15-20 minutes there. --thesis-size runs thesis_tables at the thesis's image size (a GPU's
work); its summary is not copied to docs/benchmarks.md, whose figures are the standard run's.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import os
import platform
import shutil
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
os.environ.setdefault("GRPC_VERBOSITY", "ERROR")

import common  # noqa: E402
import gpu_run  # noqa: E402
import gpu_seeds  # noqa: E402
from common import Result, Settings, Target  # noqa: E402

CASES = ["demo", "overhead", "frozen", "warm_start", "quality", "stability", "memory", "control_plane",
         "grids", "tutorials", "shape_tutorial", "switching", "worker_restart", "two_workers", "gpu_packing", "geometry", "scheduling",
         "ray_cluster",
         "thesis_tables", "starts", "real_scenes", "defaults_matrix", "information", "calibration"]
DOCS = common.ROOT / "docs" / "benchmarks.md"
HISTORY = DOCS.with_name("benchmarks-history.md")  # by hand: a full run never writes it
# Cases no longer run, and why: the summary says so, so that a reader of an older report
# knows where its figures went.
RETIRED = {
    "live_scenes": "measured a job's iterations while the daemon kept 4 other scenes loaded "
                   "in the same process (0.99x: no measurable cost at 48x48). Since the "
                   "renderer runs in worker processes, a worker holds at most one job and "
                   "drops its preview scene when a job starts, so no other scene is ever "
                   "loaded beside a running job; what one job resident per worker costs is "
                   "the switch between jobs, which `switching` measures.",
}


def run_case(name: str, settings: Settings) -> tuple[Result, object]:
    """One case on a daemon of its own; an exception becomes a failed result rather than
    ending the run. Also returns the daemon's ServerInfo (None if it did not start)."""
    began = time.perf_counter()
    print(f"bench: {name} ...", file=sys.stderr, flush=True)
    info = None
    try:
        module = importlib.import_module(name)
        if not getattr(module, "NEEDS_DAEMON", True):  # a simulation: nothing to start
            result = module.run(settings, None)
        else:
            options = dict(getattr(module, "DAEMON", {}))
            if settings.variant:
                options["extra"] = (*options.get("extra", ()), "--variant", settings.variant)
            with common.daemon(settings.work, name, **options) as daemon:
                info = daemon.client.info
                print(f"bench: daemon {info.variant} on {info.device}, {len(info.workers)} "
                      "worker(s)", file=sys.stderr, flush=True)
                result = module.run(settings, daemon)
    except Exception as exc:  # noqa: BLE001 - reported in the summary
        traceback.print_exc()
        result = Result(name, name, [Target("case ran", f"FAILED: {type(exc).__name__}: {exc}",
                                            False)])
    result.seconds = time.perf_counter() - began
    print(f"bench: {name} done in {result.seconds:.0f} s", file=sys.stderr, flush=True)
    for t in result.targets:
        print(f"  {_mark(t.met)} {t.what}: {t.figure}", file=sys.stderr, flush=True)
    return result, info


def clear(out: Path) -> None:
    """Removes what an earlier run wrote to ``out`` (and only that), so that no stale plot
    of a case that was renamed or dropped stays next to the new summary."""
    for f in [*out.glob("*.csv"), *out.glob("*.png"), out / "summary.md"]:
        f.unlink(missing_ok=True)
    shutil.rmtree(out / "quality", ignore_errors=True)


def _stopped(signum, frame) -> None:
    raise common.Stopped("stopped at its time cap")


def _mark(met: bool | None) -> str:
    return {True: "met", False: "MISSED", None: "n/a"}[met]


def _rel(path: Path, settings: Settings) -> str:
    return Path(path).resolve().relative_to(settings.out).as_posix()


def summary(results: list[Result], settings: Settings, info, seconds: float,
            load: tuple[float, float], links: str = "", history: str = "") -> str:
    """The markdown summary; ``links`` prefixes file links (for a copy elsewhere), and
    ``history`` names the page of earlier runs, linked from the copy in docs/."""
    when = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    out = [
        "# matopt benchmarks",
        "",
        f"Latest {'quick (smoke) ' if settings.quick else ''}run of `python bench/run.py"
        f"{' --quick' if settings.quick else ''}{' --thesis-size' if settings.thesis_size else ''}"
        f"`: {when}, {seconds / 60:.1f} min.",
        (f"Daemon: {info.variant} on {info.device} ({len(info.workers)} worker process(es) "
         f"by default); matopt {info.version}, commit " if info else "Daemon: none started "
         "(it failed, or no case run needed one); commit ")
        + f"{common.git_revision()}; Python {platform.python_version()}, "
        f"{os.cpu_count()} CPU threads.",
        "",
        "Every figure is a ratio against a baseline measured in the same run, alternating "
        "with it (A B, B A, ...): the machines here are shared and noisy, so absolute times "
        "are given for context only. Load average (1 min) at the start and end of the run: "
        f"{load[0]:.1f}, {load[1]:.1f} on {os.cpu_count()} CPU threads; other work on the "
        "machine shows up as noise in every time below.",
        "",
        "Run it: `python bench/run.py` (the full run; it also rewrites docs/benchmarks.md) or "
        "`python bench/run.py --quick` (a smoke run of reduced cases, a few minutes); "
        "`--out DIR` writes elsewhere, `--only CASE ...` runs some cases, `--thesis-size` runs "
        "thesis_tables at the thesis's image size (256 px: a GPU's work), `--gpu` the figures "
        "owed on a GPU within one short loan of a machine (docs/developing.md, \"A GPU run\"; "
        "its section, spliced in with `--splice`, outlives a full run). It starts a daemon "
        "per case on a loopback port (the renderer in its worker processes, the API in the "
        "daemon's own: CPU figures name which), uses the GPU when that daemon reports a CUDA "
        "variant, and needs matplotlib (`pip install 'matopt-mitsuba[plot]'`). The cases are the "
        "modules in `bench/`; each module's docstring says exactly what it measures and why.",
        "",
        *([f"Earlier runs, what changed between them, and the experiments behind the engine's "
           f"choices: [{history}]({history}).", ""] if history else []),
        "## Targets",
        "",
        "| case | figure | result | met |",
        "|---|---|---|---|",
    ]
    for r in results:
        for t in r.targets:
            out.append(f"| {r.name} | {t.what} | {t.figure} | {_mark(t.met)} |")
    for r in results:
        out += ["", f"## {r.title} (`bench/{r.name}.py`, {r.seconds:.0f} s)", ""]
        out += r.lines
        pictures = [f for f in r.files if f.suffix == ".png"]
        tables = [f for f in r.files if f.suffix == ".csv"]
        if tables:
            out += ["", "Data: " + ", ".join(f"[{_rel(f, settings)}]({links}{_rel(f, settings)})"
                                             for f in tables)]
        for f in pictures:
            out += ["", f"![{_rel(f, settings)}]({links}{_rel(f, settings)})"]
    out += ["", "## Retired cases", ""]
    out += [f"- `{name}`: {why}" for name, why in RETIRED.items()]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="reduced cases: a smoke run")
    p.add_argument("--out", type=Path, default=HERE / "results", help="results directory")
    p.add_argument("--only", nargs="+", choices=CASES, help="run only these cases")
    p.add_argument("--thesis-size", action="store_true",
                   help="thesis_tables at the thesis's image size (256 px; hours on a CPU)")
    p.add_argument("--thesis-repo", type=Path, metavar="DIR",
                   help="a checkout of github.com/sapo17/BachelorThesis (real_scenes)")
    p.add_argument("--tutorials-repo", type=Path, metavar="DIR",
                   help="a checkout of github.com/mitsuba-renderer/mitsuba-tutorials (tutorials)")
    p.add_argument("--variant", default="",
                   help="the daemons' and plain loops' Mitsuba variant, e.g. cuda_ad_rgb")
    p.add_argument("--film", metavar="WxH", help="real_scenes: the film rendered (default "
                   "683x512 on a GPU, 128x96 on the CPU); frozen: its thesis scenes' one size")
    p.add_argument("--iterations", type=int, default=0,
                   help="real_scenes: iterations per run (default 150 on a GPU, 100 on the CPU)")
    p.add_argument("--seeds", type=int, default=0, help="real_scenes: seeds (default 3)")
    p.add_argument("--tables", nargs="+", metavar="TABLE", default=(),
                   help="real_scenes, defaults_matrix, frozen: only these of the thesis's tables, e.g. "
                   "table4 (default: all)")
    p.add_argument("--defaults-only", action="store_true",
                   help="real_scenes: only the plain loop and the daemon's defaults per seed "
                   "(no choices turned off, no plain preset, no equal-work pairs)")
    p.add_argument("--cost-only", action="store_true",
                   help="calibration: only the cost of the standard errors")
    p.add_argument("--deadline", type=float, default=0.0, help=argparse.SUPPRESS)
    p.add_argument("--result-json", type=Path, help=argparse.SUPPRESS)  # for --gpu's children
    p.add_argument("--gpu", action="store_true",
                   help="the figures owed on a GPU, each case with a time cap, within --budget "
                   "(bench/gpu_run.py); writes --out only")
    p.add_argument("--budget", type=float, default=gpu_run.BUDGET, help="--gpu: seconds in all")
    p.add_argument("--cap-scale", type=float, default=1.0,
                   help="--gpu: each case's time cap times this (a check on a slower machine)")
    p.add_argument("--splice", type=Path, metavar="DIR",
                   help="copy a --gpu run's output DIR to bench/results/gpu/ and its section "
                   "into docs/benchmarks.md")
    p.add_argument("--add-seeds", action="store_true",
                   help="--splice: add the run's real_scenes seeds to those of the tables before "
                   "(a seed run again replaces its rows; the other cases stay as they were)")
    p.add_argument("--with-choice", action="append", default=[], metavar="NAME=VALUE",
                   help="real_scenes, defaults_matrix: also a daemon job per seed with this "
                   "choice set (e.g. gauss_newton=on) or JobSpec field (schedule=constant), "
                   "beside the defaults; stability: each stiff case again with it")
    p.add_argument("--paths", action="store_true",
                   help="defaults_matrix: keep every run's values per iteration "
                        "(defaults_matrix-paths.jsonl in --out)")
    p.add_argument("--thesis-bounds", action=argparse.BooleanOptionalAction, default=True,
                   help="real_scenes, defaults_matrix: the daemon's jobs get the thesis's bounds "
                   "the plain loop runs with (Table 4's eta at most 1.55, its start), so that "
                   "both sides solve one problem (default); --no-thesis-bounds leaves them to "
                   "the plain loop alone, as the rows before 2026-12-01 were run")
    p.add_argument("--candidate-only", action="store_true",
                   help="defaults_matrix, stability: the --with-choice job in place of the "
                   "defaults, judged as they are (the plain loop at equal time runs for its "
                   "time)")
    p.add_argument("--first-seed", type=int, default=0,
                   help="real_scenes, defaults_matrix: the first seed run (the others follow it)")
    p.add_argument("--spp", type=int, nargs="+", default=(), metavar="SPP",
                   help="defaults_matrix: the spp of its cells (default 8 16; the full "
                   "matrix: 8 16 32)")
    p.add_argument("--depth", type=int, nargs="+", default=(), metavar="DEPTH",
                   help="defaults_matrix: the max_depth of its cells (default 8 64)")
    args = p.parse_args(argv)
    for c in args.with_choice:
        if "=" not in c:
            p.error(f"--with-choice wants NAME=VALUE, got {c!r}")
    if args.candidate_only and not args.with_choice:
        p.error("--candidate-only runs the --with-choice job in the defaults' place: "
                "name one with --with-choice NAME=VALUE")
    try:  # a bad candidate says so here, not after a daemon started and a case ran
        common.candidate(dict(c.split("=", 1) for c in args.with_choice))
    except ValueError as e:
        p.error(f"--with-choice {e}")
    if args.splice:
        return (gpu_seeds.add if args.add_seeds else gpu_run.splice)(args.splice, DOCS)
    if args.gpu:
        if args.out == HERE / "results":
            args.out = gpu_run.RESULTS
        return gpu_run.run_all(args)
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.only:
        clear(args.out)
    work = Path(tempfile.mkdtemp(prefix="matopt-bench-"))
    film = tuple(int(x) for x in args.film.lower().split("x")) if args.film else None
    settings = Settings(args.out.resolve(), args.quick, work, args.thesis_size,
                        args.thesis_repo.resolve() if args.thesis_repo else None, args.variant,
                        film, args.iterations, args.seeds, tuple(args.tables),
                        args.defaults_only, args.cost_only, args.deadline,
                        dict(c.split("=", 1) for c in args.with_choice), args.first_seed,
                        tuple(args.spp), tuple(args.depth),
                        args.tutorials_repo.resolve() if args.tutorials_repo else None,
                        args.candidate_only, args.paths, args.thesis_bounds)
    if args.result_json:  # a case of --gpu, stopped at its cap with SIGTERM: say what finished
        signal.signal(signal.SIGTERM, _stopped)
    began = time.perf_counter()
    load_before = os.getloadavg()[0]
    results, info = [], None
    try:
        for name in args.only or CASES:
            result, started = run_case(name, settings)
            results.append(result)
            info = info or started
    finally:
        shutil.rmtree(work, ignore_errors=True)
    seconds = time.perf_counter() - began
    load = (load_before, os.getloadavg()[0])
    text = summary(results, settings, info, seconds, load)
    (settings.out / "summary.md").write_text(text)
    if args.result_json:
        gpu_run.save_result(results[0], info, args.result_json)
    print(f"bench: wrote {settings.out / 'summary.md'} ({seconds / 60:.1f} min)", file=sys.stderr)
    if not (args.quick or args.only or args.thesis_size) and settings.out == (HERE / "results").resolve():
        links = os.path.relpath(settings.out, DOCS.parent) + "/"
        # The GPU section (--splice) stays: this run does not measure it.
        gpu = gpu_run.current(DOCS.read_text()) if DOCS.exists() else ""
        DOCS.write_text(summary(results, settings, info, seconds, load, links, HISTORY.name)
                        + ("\n" + gpu if gpu else ""))
        print(f"bench: copied the summary to {DOCS}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
