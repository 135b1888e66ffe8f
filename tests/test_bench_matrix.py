"""bench/defaults_matrix's judgement of a cell, from runs as data (no daemon): against the
plain loop at equal time, and the parameters' own gate, Table 2's 1% and Table 4's 2%, held
to the end by the median seed."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import defaults_matrix as dm  # noqa: E402
import real_scenes as rs  # noqa: E402

TABLES = {t.name: t for t in rs.TABLES}


def _run(table: rs.Table, method: str, seed: int, errors: list[float]) -> rs.Run:
    """A run whose gated parameters all have the given relative error per iteration (1 s)."""
    return rs.Run(table.name, method, seed, 1.0, [float(i) for i in range(len(errors))],
                  [{k: e for k in table.targets} for e in errors], len(errors), {}, 1.0)


def _cell(table: rs.Table, daemon: list[list[float]], plain: list[float]) -> dm.Cell:
    runs = [_run(table, "daemon", s, e) for s, e in enumerate(daemon)]
    for s in range(len(daemon)):
        runs += [_run(table, rs.EQUAL_TIME, s, plain), _run(table, "plain", s, plain)]
    return dm.Cell(table.name, 8, 16, runs)


@pytest.mark.parametrize("table, end, held", [
    ("table2", 0.015, False),  # within 2%, not 1%: Table 2's gate is 1%
    ("table2", 0.008, True),
    ("table4", 0.015, True),   # Table 4's is 2%
    ("table4", 0.03, False)])
def test_a_cell_holds_its_tables_gate_where_the_median_seed_ends_and_stays_within_it(
        table, end, held):
    t = TABLES[table]
    good = [0.5, 0.1, end, end]
    row, met, gate = dm.judge(t, _cell(t, [good, good, [0.5, 0.5, 0.5, 0.5]], [0.5] * 4))
    assert gate is held
    assert met  # the defaults end below the plain loop's 50% and reach 2% where it never does
    assert row.endswith(f"| {'met' if held else 'MISSED'} |")



def test_a_cell_counts_the_seeds_the_defaults_win_against_the_plain_loop_on_the_same_seed():
    """The median of a few seeds falls either way where they spread widely: the row also says
    on how many seeds the defaults end at most at the plain loop's worst at equal time, each
    seed against its own (the same samples per iteration)."""
    t = TABLES["table4"]
    runs = [_run(t, "daemon", s, [e]) for s, e in enumerate([0.03, 0.05, 0.04])]
    runs += [_run(t, rs.EQUAL_TIME, s, [e]) for s, e in enumerate([0.10, 0.02, 0.04])]
    runs += [_run(t, "plain", s, [0.5]) for s in range(3)]
    cell = dm.Cell(t.name, 64, 8, runs)
    assert dm.won(t, cell) == 2                      # seeds 0 and 2 (a tie counts)
    row, _, _ = dm.judge(t, cell)
    assert "| 2 of 3 |" in row


def test_a_candidate_names_choices_and_jobspec_settings_and_a_bad_value_says_what_is_legal():
    import common
    choices, fields = common.candidate({"schedule": "constant", "learning_rate": "0.05",
                                        "gauss_newton": "on"})
    assert choices == {"gauss_newton": "on"}
    assert fields == {"schedule": common.pb.SCHEDULE_CONSTANT, "learning_rate": 0.05}
    with pytest.raises(ValueError, match="schedule=linear: not one of .*SCHEDULE_COSINE"):
        common.candidate({"schedule": "linear"})
    spec = common.pb.JobSpec(seed=3)
    for name, value in fields.items():
        setattr(spec, name, value)
    assert spec.schedule == common.pb.SCHEDULE_CONSTANT and spec.learning_rate == pytest.approx(0.05)


def test_a_bad_candidate_stops_the_bench_before_any_case_runs(capsys):
    import run
    for argv, said in ((["--with-choice", "schedule=linear"],
                        "not one of SCHEDULE_UNSPECIFIED, SCHEDULE_COSINE"),
                       (["--with-choice", "gauss_newton"],
                        "wants NAME=VALUE, got 'gauss_newton'"),
                       # without a candidate it would run the defaults and call them one
                       (["--candidate-only"], "name one with --with-choice NAME=VALUE")):
        with pytest.raises(SystemExit) as stopped:
            run.main(["--only", "defaults_matrix", *argv])
        assert stopped.value.code == 2
        assert said in capsys.readouterr().err


def test_an_unbounded_cell_loads_the_scene_file_as_a_user_does_and_a_set_depth_is_set():
    # A max_depth among a scene's overrides is the user's, which the daemon's depth choice
    # leaves alone; the unbounded cell must leave it unset for that choice to be judged.
    assert dm.scene_overrides(-1) == {}
    assert dm.scene_overrides(8) == {"max_depth": "8"}
    assert dm.scene_overrides(64) == {"max_depth": "64"}


def test_a_cells_paths_are_written_a_line_per_run_and_read_back_as_they_were(tmp_path):
    """--paths: each run's values at every iteration, with where and which run it was."""
    table = TABLES["table4"]
    cell = _cell(table, [[0.1, 0.05], [0.2, 0.01]], [0.3, 0.02])
    for n, r in enumerate(cell.runs):
        r.paths = [{k: [0.1 * n + i] * len(v) for k, v in table.truth.items()}
                   for i in range(len(r.seconds))]
    file = tmp_path / "out" / "defaults_matrix-paths.jsonl"
    dm.write_paths(file, dm.path_rows(cell))
    back = dm.read_paths(file)
    assert len(back) == len(cell.runs) == 6
    for row, r in zip(back, cell.runs):
        assert (row["table"], row["depth"], row["spp"], row["method"], row["seed"]) == (
            "table4", 8, 16, r.method, r.seed)
        assert row["values"] == r.paths and row["seconds"] == r.seconds


def test_the_thesis_bounds_reach_the_daemons_jobs_by_default_and_leave_them_when_asked():
    """By default the daemon's jobs get Table 4's eta <= 1.55, as its plain loop does (both
    sides solve one problem); --no-thesis-bounds leaves it to the plain preset (equal work)."""
    table = TABLES["table4"]
    eta = "object_bsdf.eta"

    def spec(thesis_bounds: bool, **kw):
        prep = rs.Prepared(table, rs.pb.Scene(name="scenes/s"), "blobs/r", Path("r.exr"),
                           Path("s.xml"), {}, {}, thesis_bounds)
        return {p.key: p for p in rs.daemon_spec(prep, 0, 10, **kw).parameters}

    assert spec(False)[eta].HasField("max") is False
    assert spec(True)[eta].max == pytest.approx(1.55)
    assert not spec(True)["medium1.sigma_t.value.value"].HasField("max")
    assert spec(False, preset_plain=True)[eta].max == pytest.approx(1.55)
