"""``bench/run.py --gpu`` and ``--splice`` (bench/gpu_run.py): a case's result goes from its
child process to the section intact; the section lands in the results page once, replaces
itself on the next splice, and outlives a full CPU run's rewrite of the page; a case past its
cap is stopped with its daemons and reported."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import gpu_run  # noqa: E402
from common import Result, Target  # noqa: E402

HEAD = {"when": "2026-11-27 15:00 UTC", "quick": False, "budget": 510, "scale": 1.0,
        "card": "NVIDIA H100 80GB HBM3, 81559 MiB, 570.86", "variant": "cuda_ad_rgb",
        "device": "CUDA device 0", "version": "0.1.0", "minutes": 7.5}


def _result(out: Path, figure: str) -> Result:
    csv = out / "cases" / "demo" / "demo.csv"
    csv.parent.mkdir(parents=True, exist_ok=True)
    csv.write_text("run,seconds\n0,1.5\n")
    return Result("demo", "The demo's time", [Target("demo time", figure, True)],
                  ["- later runs: 1.5 s"], [csv], 12.0)


def test_a_result_comes_back_from_its_child_as_it_was(tmp_path):
    result = _result(tmp_path, "1.5 s")
    info = SimpleNamespace(variant="cuda_ad_rgb", device="CUDA device 0", version="0.1.0")
    gpu_run.save_result(result, info, tmp_path / "result.json")
    back, got = gpu_run.load_result(tmp_path / "result.json")
    assert back == result
    assert got == {"variant": "cuda_ad_rgb", "device": "CUDA device 0", "version": "0.1.0"}


def test_the_section_is_spliced_once_replaced_and_kept_by_a_full_run(tmp_path, monkeypatch):
    out = tmp_path / "back" / "gpu"
    monkeypatch.setattr(gpu_run, "RESULTS", tmp_path / "results" / "gpu")
    docs = tmp_path / "benchmarks.md"
    docs.write_text("# matopt benchmarks\n\n## Targets\n")
    for figure in ("1.5 s", "1.4 s"):
        (out / "summary.md").parent.mkdir(parents=True, exist_ok=True)
        (out / "summary.md").write_text(gpu_run.section([_result(out, figure)], out, HEAD, True))
        gpu_run.splice(out, docs)
    page = docs.read_text()
    assert page.count(gpu_run.BEGIN) == 1 and page.count(gpu_run.END) == 1
    assert "| demo | demo time | 1.4 s | met |" in page and "1.5 s |" not in page
    assert "Card: NVIDIA H100 80GB HBM3" in page and page.startswith("# matopt benchmarks")
    assert "[cases/demo/demo.csv](../bench/results/gpu/cases/demo/demo.csv)" in page
    assert (tmp_path / "results" / "gpu" / "cases" / "demo" / "demo.csv").exists()
    # A full CPU run writes the page anew from its own summary and appends the kept section.
    rewritten = "# matopt benchmarks\n\n## Targets\n(new)\n" + "\n" + gpu_run.current(page)
    assert gpu_run.current(rewritten) == gpu_run.current(page) != ""


def test_splice_refuses_a_folder_that_is_not_a_gpu_run(tmp_path):
    (tmp_path / "summary.md").write_text("# matopt benchmarks\n")
    with pytest.raises(SystemExit, match="not the output of run.py --gpu"):
        gpu_run.splice(tmp_path, tmp_path / "benchmarks.md")


def test_a_case_past_its_cap_is_stopped_and_reported(tmp_path, monkeypatch):
    """The child (here a sleeper standing in for run.py) is stopped at its cap, whole, and
    the report says how far it got."""
    sleeper = tmp_path / "sleeper.py"
    grandchild = tmp_path / "grandchild.pid"
    sleeper.write_text("import subprocess, sys, time\n"
                       "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'],"
                       " start_new_session=True)\n"
                       f"open({str(grandchild)!r}, 'w').write(str(p.pid))\n"
                       "print('bench: frozen 32x32: 4.8 ms', flush=True)\n"
                       "time.sleep(60)\n")
    monkeypatch.setattr(gpu_run, "__file__", str(sleeper.with_name("gpu_run.py")))
    sleeper.rename(sleeper.with_name("run.py"))
    args = SimpleNamespace(quick=False, variant="", thesis_repo=None)
    began = time.perf_counter()
    result = gpu_run.child("demo", (), args, tmp_path / "demo", 3)
    assert time.perf_counter() - began < 30
    # where it was when stopped: its log's last line
    assert result.targets == [Target("case ran", "FAILED: stopped at its cap of 3 s; its log's "
                                     "last: bench: frozen 32x32: 4.8 ms", False)]
    pid = int(grandchild.read_text())  # in a session of its own, as matopt demo's daemon
    for _ in range(50):
        if not Path(f"/proc/{pid}").exists() or "Z" in _state(pid):
            break
        time.sleep(0.1)
    assert not Path(f"/proc/{pid}").exists() or "Z" in _state(pid)


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "Z"


def test_real_scenes_stopped_at_its_cap_reports_the_seeds_that_ended(tmp_path, monkeypatch):
    """The cap's SIGTERM (common.Stopped) in the middle of a table's second seed: the first
    seed's figures are reported, the unfinished seed is left out, and no table begins."""
    import real_scenes as rs
    from common import Settings, Stopped

    table2 = rs.TABLES[0]

    def run(method: str, seed: int, error: float) -> rs.Run:
        return rs.Run(table2.name, method, seed, 0.3, [0.0, 1.0],
                      [{k: 0.5 for k in table2.truth}, {k: error for k in table2.truth}],
                      2, {}, 0.3)

    def measure(table, p, settings, server, deadline=0.0, runs=None):
        assert table is table2  # table4 is never begun
        runs += [run("plain", 0, 0.04), run("daemon", 0, 0.005), run(rs.EQUAL_TIME, 0, 0.03),
                 run("plain", 1, 0.04)]
        raise Stopped("stopped at its time cap")

    monkeypatch.setattr(rs, "measure", measure)
    settings = Settings(tmp_path, False, tmp_path, thesis_repo=tmp_path)
    result = rs.run(settings, SimpleNamespace(variant="cuda_ad_rgb"))
    figures = {t.what: t.figure for t in result.targets}
    assert figures["table2: stopped"] == "at the time cap, 1 seed(s) ended before it"
    assert not any(w.startswith("table4") for w in figures), figures
    assert any(w.startswith("GPU table2") for w in figures), figures  # seed 0's figure
    rows = (tmp_path / "real_scenes.csv").read_text().splitlines()
    assert len(rows) == 1 + 3  # the header and seed 0's three runs; seed 1's plain left out


def test_a_run_of_some_cases_keeps_the_other_cases_of_the_run_before(tmp_path, monkeypatch):
    """A loan's run of the demo alone replaces the demo's figure and file, and keeps
    overhead's from the run before, saying which run that was; a later run of overhead alone
    leaves the demo's attributed to the run that made it, and no line for the first."""
    monkeypatch.setattr(gpu_run, "RESULTS", tmp_path / "results" / "gpu")
    docs = tmp_path / "benchmarks.md"
    docs.write_text("# matopt benchmarks\n")
    first, second = tmp_path / "first" / "gpu", tmp_path / "second" / "gpu"
    first.mkdir(parents=True)
    csv = first / "cases" / "overhead" / "overhead.csv"
    csv.parent.mkdir(parents=True)
    csv.write_text("round,ratio\n0,0.28\n")
    overhead = Result("overhead", "Daemon overhead per iteration",
                      [Target("daemon / plain loop", "0.280", True)], ["- ratio 0.280"], [csv])
    earlier = HEAD | {"when": "2026-11-28 20:14 UTC"}
    (first / "summary.md").write_text(gpu_run.section([_result(first, "5.9 s"), overhead],
                                                      first, earlier, True))
    gpu_run.splice(first, docs)
    # The run's line rewritten by hand on the page is the one a later splice keeps.
    docs.write_text(docs.read_text().replace("`python bench/run.py --gpu` (finished): 2026-11-28",
                                             "One run on a loan, 2026-11-28"))
    second.mkdir(parents=True)
    (second / "summary.md").write_text(gpu_run.section([_result(second, "4.1 s")], second,
                                                       HEAD, True))
    gpu_run.splice(second, docs)
    page = docs.read_text()
    assert "| demo | demo time | 4.1 s | met |" in page and "5.9 s" not in page
    assert "| overhead | daemon / plain loop | 0.280 | met |" in page
    assert "### Daemon overhead per iteration (`bench/overhead.py`" in page
    assert "Earlier, for overhead: One run on a loan, 2026-11-28 20:14 UTC" in page
    assert page.count("### The demo's time") == 1 and page.count(gpu_run.BEGIN) == 1
    assert (tmp_path / "results" / "gpu" / "cases" / "overhead" / "overhead.csv").exists()
    # Overhead run again alone: the demo is the second run's, and nothing names the first.
    again = second / "cases" / "overhead" / "overhead.csv"
    again.parent.mkdir(parents=True)
    again.write_text("round,ratio\n0,0.27\n")
    overhead.files, overhead.targets = [again], [Target("daemon / plain loop", "0.270", True)]
    third = HEAD | {"when": "2026-11-30 01:20 UTC"}
    (second / "summary.md").write_text(gpu_run.section([overhead], second, third, True))
    gpu_run.splice(second, docs)
    page = docs.read_text()
    assert "| overhead | daemon / plain loop | 0.270 | met |" in page
    assert "| demo | demo time | 4.1 s | met |" in page
    assert "Earlier, for demo: `python bench/run.py --gpu` (finished): 2026-11-27 15:00" in page
    assert "2026-11-28 20:14" not in page and page.count("Earlier, for") == 1
    (second / "summary.md").write_text(gpu_run.section(
        [_result(second, "4.0 s"), overhead], second, HEAD, True))
    gpu_run.splice(second, docs)
    assert "Earlier, for" not in docs.read_text()


def test_a_failure_message_of_several_lines_stays_in_its_table_row(tmp_path):
    failed = Result("frozen", "frozen", [Target("case ran", "FAILED: RpcError:\n\tstatus = "
                                                 "RESOURCE_EXHAUSTED | limit", False)])
    text = gpu_run.section([failed], tmp_path, HEAD, True)
    row = [ln for ln in text.splitlines() if ln.startswith("| frozen |")]
    assert row == ["| frozen | case ran | FAILED: RpcError: status = RESOURCE_EXHAUSTED \\| "
                   "limit | MISSED |"]
