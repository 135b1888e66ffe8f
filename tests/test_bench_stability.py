"""bench/stability's candidate runs: each stiff case again with a candidate default set over
the case's own choices, under a name of its own (no daemon: the cases as data)."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import stability  # noqa: E402
import stiff  # noqa: E402


def test_a_candidate_case_sets_its_choice_over_the_cases_own_and_keeps_the_rest():
    case = stiff.Case("x", "<scene/>", {"k": [0.5]}, {"k": [0.2]}, 10,
                      spec={"spp": 4, "choices": {"log_space": "off", "frozen": "off"}})
    trial = stability._candidate(case, {"frozen": "on", "eta_differences": "quarter:0.05"})
    assert trial.name == "x, candidate"
    assert trial.spec == {"spp": 4, "choices": {"log_space": "off", "frozen": "on",
                                                "eta_differences": "quarter:0.05"}}
    assert case.spec["choices"] == {"log_space": "off", "frozen": "off"}  # its own untouched
    assert (trial.start, trial.truth, trial.iterations) == (case.start, case.truth, 10)


def test_a_candidate_may_be_a_jobspec_setting_as_well_as_a_choice():
    case = stiff.Case("x", "<scene/>", {"k": [0.5]}, {"k": [0.2]}, 10, spec={"spp": 4})
    trial = stability._candidate(case, {"schedule": "constant", "eta_hold": "off"})
    assert trial.spec == {"spp": 4, "schedule": stability.common.pb.SCHEDULE_CONSTANT,
                          "choices": {"eta_hold": "off"}}
