"""The scene's integrator is the user's choice: a job renders with it and its properties
whenever it differentiates the selected parameters, and says what it replaced and why when it
does not (engine/integrator.py), through a real daemon."""

from __future__ import annotations

import pytest

from test_materials import recover
from scenes import QUAD_CORNERS, QUAD_IN_FRONT, quad_obj

SPPI0 = ('<integrator type="direct_projective"><integer name="sppi" value="0"/>'
         '<boolean name="hide_emitters" value="true"/></integrator>')


def _quad(integrator: str) -> dict[str, bytes]:
    return {"quad.xml": QUAD_IN_FRONT.replace('<integrator type="direct"/>', integrator).encode(),
            "quad.obj": quad_obj()}


def _replaced(done) -> list[str]:
    return [n for n in done.notes if n.startswith("integrator:")]


def test_a_projective_integrator_of_the_scene_renders_vertex_positions_as_it_stands(stubs):
    """Mitsuba's own shape example sets sppi 0 on direct_projective: the job keeps it (and
    hide_emitters), which a replacement with Mitsuba's defaults (sppi = spp) would not."""
    start = [c + d for corner in QUAD_CORNERS for c, d in zip(corner, (0.1, 0.0, 0.0))]
    _, _, done = recover(stubs, _quad(SPPI0), "quad.xml", {"quad.vertex_positions": start},
                         iterations=2, spp=2, reference_spp=16)
    assert done.integrator == "direct_projective"
    assert "the scene's direct_projective as it stands (sppi 0)" in done.integrator_reason
    assert not _replaced(done), done.notes


@pytest.mark.parametrize("integrator, key, expect, said", [
    # not differentiable: its differentiable counterpart, with the scene's depth
    ('<integrator type="path"><integer name="max_depth" value="3"/>'
     '<integer name="rr_depth" value="2"/></integrator>', "quad.bsdf.reflectance.value", "prb",
     "integrator: prb instead of the scene's path, which is not differentiable"),
    # prb cannot sample the silhouettes of a moving edge
    ('<integrator type="prb"><integer name="max_depth" value="2"/></integrator>',
     "quad.vertex_positions", "direct_projective",
     "integrator: direct_projective instead of the scene's prb, which does not sample the "
     "silhouettes"),
])
def test_an_integrator_that_cannot_differentiate_is_replaced_and_the_notes_say_why(
        stubs, integrator, key, expect, said):
    start = ([0.5, 0.5, 0.5] if key.endswith("value") else
             [c for corner in QUAD_CORNERS for c in corner])
    _, _, done = recover(stubs, _quad(integrator), "quad.xml", {key: start}, iterations=1,
                         spp=2, reference_spp=8)
    assert done.integrator == expect, done.integrator_reason
    notes = _replaced(done)
    assert len(notes) == 1 and notes[0].startswith(said), done.notes
    assert "carried over: max_depth" in notes[0]
    if expect == "prb":
        assert "max_depth 3 (the scene's)" in done.integrator_reason
