"""The benchmark cases' shared helpers that decide a figure: a loop at equal time stops when
its time is up, a method's rows are grouped by method, and the shape tutorial's Chamfer
distance measures what it says."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import common  # noqa: E402
import plain  # noqa: E402
import shape_tutorial  # noqa: E402


def test_a_loop_at_equal_time_stops_when_its_time_is_up_and_not_before(monkeypatch):
    assert list(plain.iterations(4, time.perf_counter())) == [0, 1, 2, 3]
    # time left for every iteration: as many as the cap allows
    assert len(list(plain.iterations(4, time.perf_counter(), seconds=60.0, cap=3))) == 12
    # the time already spent (the scene's load counts): none begins
    assert list(plain.iterations(4, time.perf_counter() - 5.0, seconds=1.0)) == []
    # iterations of 0.02 s on a clock of its own (a busy machine's sleeps would overshoot):
    # those beginning at 0, 0.02 and 0.04 fit in 0.05 s, the one at 0.06 does not
    clock = iter(0.02 * i for i in range(100))
    monkeypatch.setattr(plain.time, "perf_counter", lambda: next(clock))
    assert list(plain.iterations(100, 0.0, seconds=0.05)) == [0, 1, 2]


def test_rows_are_grouped_by_method_in_seed_order():
    rows = [{"seed": s, "method": m, "error": e} for s, m, e in
            [(0, "a", 0.1), (0, "b", 0.2), (1, "a", 0.3), (1, "b", 0.4)]]
    got = common.by_method(rows, ["b", "a"])
    assert list(got) == ["b", "a"]
    assert got["a"]["error"] == [0.1, 0.3] and got["b"]["seed"] == [0, 1]


def test_the_chamfer_distance_is_symmetric_and_zero_only_for_the_same_points():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(300, 3)).astype(np.float32)
    assert shape_tutorial.chamfer(a, a) == 0.0
    shifted = a + np.float32([0.01, 0, 0])  # every nearest point is its own copy, 0.01 away
    assert abs(shape_tutorial.chamfer(a, shifted) - 0.01) < 1e-4
    b = rng.normal(size=(120, 3)).astype(np.float32)
    assert shape_tutorial.chamfer(a, b) == shape_tutorial.chamfer(b, a) > 0.05
