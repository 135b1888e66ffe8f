"""The notes a job gives about ranges: a value that ended on a bound, a start value clipped."""

from __future__ import annotations

import math

import numpy as np

from matoptd.range_notes import bound_notes, clip_note


def test_a_value_within_float32_precision_of_its_bound_is_on_it():
    # 1000 as float32 arithmetic leaves it: one unit in the last place below the bound.
    near = np.nextafter(np.float32(1000.0), np.float32(0.0))
    notes = bound_notes("light.radiance", np.array([near, 500.0], np.float32), 0.0, 1000.0)
    assert len(notes) == 1
    assert "light.radiance: 1 of 2 component(s) ended on its upper bound 1000" in notes[0]
    assert "widen its range" in notes[0] and "fix the parameter" in notes[0]
    assert bound_notes("light.radiance", np.array([999.0]), 0.0, 1000.0) == []


def test_both_bounds_and_infinite_ones():
    notes = bound_notes("wall.reflectance", np.array([0.0, 1.0, 0.5]), 0.0, 1.0)
    assert [n.split(":")[1].strip() for n in notes] == [
        "1 of 3 component(s) ended on its lower bound 0", "1 of 3 component(s) ended on its upper bound 1"]
    assert bound_notes("pos", np.array([1e30]), -math.inf, math.inf) == []


def test_clip_note_names_parameter_source_and_values():
    note = clip_note("wall.reflectance", np.array([1.3]), 0.0, 0.8, "the best result of jobs/a")
    assert note == ("wall.reflectance: the best result of jobs/a lies outside the job's range "
                    "[0, 0.8] and was clipped into it (from 1.3 to 0.8)")
    many = clip_note("tex.data", np.array([1.1, -0.2, 0.9]), 0.0, 1.0, "the initial value")
    assert "2 of 3 components, e.g. component 1 from -0.2 to 0" in many
    assert clip_note("tex.data", np.array([0.5, 1.0]), 0.0, 1.0, "the initial value") is None
