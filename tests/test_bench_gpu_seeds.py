"""bench/gpu_seeds: real_scenes' GPU seeds from two device loans added into one table's
figures, the other cases and tables left as they were (no daemon, no GPU)."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import gpu_run  # noqa: E402
import gpu_seeds  # noqa: E402

HEAD = ("| method | s / iteration | CPU s / iteration | to 2% staying (s) | to 1% staying (s) | "
        "final alpha | final albedo | final sigma_t | final eta |")
SCENE = ("**table4** (`scene-homogeneuous-bunny.xml`, integrator `prbvolpath`; plain loop: 8 spp"
         "; {s} s)")
DEMO = "### The demo (`bench/demo.py`, 9 s)\n\nthe demo's own text, left alone"
OTHER = "**table2** (`scene-bunny.xml`, integrator `prb`; plain loop: 16 spp; 50 s)\n\nkept as is"


def _rows(seed: int, daemon: float, plain: float, run: str | None) -> list[dict]:
    """A seed's three runs: the daemon ends with ``daemon`` as its worst gated error."""
    out = []
    for method, worst, to2 in (("plain", plain, ""), ("daemon", daemon, "90.0"),
                               ("plain, equal time", plain, "")):
        row = {"table": "table4", "method": method, "seed": seed,
               "seconds_per_iteration": 0.7, "cpu_per_iteration": 0.7, "to_2pct": to2,
               "to_1pct": "", "final:alpha": 0.5, "final:albedo": worst / 2,
               "final:sigma_t": worst, "final:eta": worst / 4, "value:eta": "1.49"}
        if run:
            row["run"] = run
        out.append(row)
    return out


def _write(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def _section(head: str, rows: list[str], real_scenes: str) -> str:
    return "\n".join([gpu_run.BEGIN, "## GPU run", "", head, "",
                      "| case | figure | result | met |", "|---|---|---|---|", *rows, "", DEMO,
                      "", "### The thesis's Tables 2 and 4 on its own scenes "
                      "(`bench/real_scenes.py`, 400 s)", "", "cuda_ad_rgb, film 683x512.", "",
                      real_scenes, gpu_run.END]) + "\n"


def test_seeds_of_a_later_loan_join_the_table_and_its_figures_are_taken_over_all(tmp_path):
    results, source, docs = tmp_path / "results", tmp_path / "source", tmp_path / "docs.md"
    # Before: seeds 0 and 2 of Table 4 from one loan, and Table 2's block.
    _write(results / "cases" / "real_scenes" / "real_scenes.csv",
           _rows(0, 0.05, 0.02, None) + _rows(2, 0.01, 0.03, None))
    old_rows = ["| demo | `matopt demo`, command to result | 4.4 s | met |",
                "| real_scenes | GPU table4: worst final error of albedo, sigma_t, eta (median), "
                "daemon vs plain at equal time | 0.0300 vs 0.0250 | MISSED |",
                "| real_scenes | table4: seeds | 2 of 3 | n/a |",
                "| real_scenes | GPU table2: base_color within 1% staying | 27.1 s vs never s "
                "| met |"]
    block4 = "\n".join([SCENE.format(s=380), "", HEAD, "old table", "",
                        "The job's integrator: old."])
    docs.write_text("# Benchmarks\n\ntext before\n\n" + _section(
        "Three runs on one loan, 2026-11-30.", old_rows,
        block4 + "\n\n" + OTHER + "\n\nData: [old](x)") + "\ntext after\n")
    # The later loan: seed 0 again (it replaces the first) and seed 1.
    _write(source / "cases" / "real_scenes" / "real_scenes.csv",
           _rows(0, 0.004, 0.02, None) + _rows(1, 0.006, 0.01, None))
    (source / "summary.md").write_text(_section(
        "`python bench/run.py --gpu` (finished): 2026-12-01 10:00 UTC, 6.0 min of a 560 s "
        "budget. Card: H200; matopt 0.1.0, commit abc1234 (when its bundle was built).",
        ["| real_scenes | table4: seeds | 2 of 3 | n/a |"],
        "\n".join([SCENE.format(s=700), "", HEAD, "new table", "",
                   "The job's integrator: prbvolpath, new.", "- choice `depth` (on): new"])))

    assert gpu_seeds.add(source, docs, results) == 0

    kept = list(csv.DictReader(open(results / "cases" / "real_scenes" /
                                    "real_scenes-table4.csv", newline="")))
    by_seed = {int(r["seed"]): r for r in kept if r["method"] == "daemon"}
    assert sorted(by_seed) == [0, 1, 2]
    assert float(by_seed[0]["final:sigma_t"]) == 0.004  # the seed run again: the later run's
    assert by_seed[0]["run"] == by_seed[1]["run"] == "2026-12-01 10:00 UTC, abc1234"
    assert by_seed[2]["run"] == "an earlier run" and by_seed[2]["value:eta"] == "1.49"
    assert not (results / "cases" / "real_scenes" / "real_scenes.csv").exists()

    page = docs.read_text()
    assert page.startswith("# Benchmarks\n\ntext before\n") and page.endswith("text after\n")
    section = gpu_run.current(page)
    assert (results / "summary.md").read_text() == section
    # The worst final error over the three seeds: daemon 0.004, 0.006, 0.01 (median 0.006),
    # the plain loop at equal time 0.02, 0.01, 0.03 (median 0.02).
    assert ("| real_scenes | GPU table4: worst final error of albedo, sigma_t, eta (median), "
            "daemon vs plain at equal time | 0.0060 vs 0.0200 | met |") in section
    assert "| real_scenes | table4: seeds | 3 (0, 1, 2), seeds 0 and 1 on 2026-12-01 10:00 UTC, " \
           "abc1234; seed 2 on an earlier run | n/a |" in section
    assert "0.0300 vs 0.0250" not in section and "2 of 3" not in section
    # The other case, the other table and the section's head stay as they were.
    assert DEMO in section and OTHER in section
    assert "| demo | `matopt demo`, command to result | 4.4 s | met |" in section
    assert "GPU table2: base_color within 1% staying | 27.1 s vs never s | met" in section
    assert "Three runs on one loan, 2026-11-30." in section
    assert "old table" not in section and "The job's integrator: prbvolpath, new." in section
    assert section.index("**table4**") < section.index("**table2**")  # the order it had
    assert "**table4** (`scene-homogeneuous-bunny.xml`, integrator `prbvolpath`; plain loop: " \
           "8 spp): seeds 0 and 1 on 2026-12-01 10:00 UTC, abc1234; seed 2 on an earlier run" \
           in section
    assert "[cases/real_scenes/real_scenes-table4.csv]" in section


def test_a_folder_without_real_scenes_is_refused_by_name_and_nothing_is_written(tmp_path):
    results, source, docs = tmp_path / "results", tmp_path / "source", tmp_path / "docs.md"
    _write(source / "cases" / "real_scenes" / "real_scenes.csv", _rows(0, 0.004, 0.02, None))
    (source / "summary.md").write_text(_section(
        "`python bench/run.py --gpu` (finished): 2026-12-01 10:00 UTC, 6.0 min. commit abc1234.",
        [], "").replace("`bench/real_scenes.py`", "`bench/other.py`"))
    docs.write_text("page\n")
    with pytest.raises(SystemExit, match=r"source/summary\.md: no real_scenes section"):
        gpu_seeds.add(source, docs, results)
    assert docs.read_text() == "page\n" and not results.exists()
