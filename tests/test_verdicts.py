"""One verdict per recovered component, the same on every surface: a value with a two-sided
interval, a one-sided one at a bound, or "not determined by these images" with the reason and
no number. The diagnosis from the job's history and the standard error are reconciled
(engine/verdicts.py): where either finds a value not decided, the result says so. A texture
that can explain the image in a scalar's place widens that scalar's interval (its smooth
modes enter J beside it)."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import finished
from scenes import camera, create_scene, exr, textured_quad

RES = 32
SEEN, AT_BOUND, HIDDEN = ("seen.bsdf.reflectance.value", "dark.bsdf.reflectance.value",
                          "hidden.bsdf.reflectance.value")


def three_quads(res: int = RES) -> str:
    """Two quads in view under a white environment (direct light only), and one out of view
    whose colour no path that reaches the camera sees at this depth."""
    return f"""<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="2"/></integrator>
    {camera(res, fov=32)}
    <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
    <shape type="rectangle" id="seen">
        <transform name="to_world"><scale value="0.5, 1, 1"/><translate value="-0.55, 0, 0"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.4, 0.2"/></bsdf>
    </shape>
    <shape type="rectangle" id="dark">
        <transform name="to_world"><scale value="0.5, 1, 1"/><translate value="0.55, 0, 0"/></transform>
        <bsdf type="diffuse"><float name="reflectance" value="0.12"/></bsdf>
    </shape>
    <shape type="rectangle" id="hidden">
        <transform name="to_world"><translate value="10, 0, 0"/></transform>
        <bsdf type="diffuse"><float name="reflectance" value="0.5"/></bsdf>
    </shape>
</scene>
"""


@pytest.fixture(scope="module")
def three(stubs) -> tuple[pb.Job, pb.JobResult]:
    """A job that ends with each verdict: the seen quad's colour two-sided, the dark one's
    (truth 0.12, range from 0.2) at its lower bound, the hidden one's not determined."""
    scene = create_scene(stubs, {"quads.xml": three_quads().encode()}, "quads.xml")
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=128)).images[0]
    return finished(stubs, pb.JobSpec(
        scene=scene.name, references=[pb.Reference(blob=ref.exr_blob)], iterations=30, spp=8,
        parameters=[pb.ParameterSpec(key=SEEN, initial_value=[0.5] * 3),
                    pb.ParameterSpec(key=AT_BOUND, initial_value=[0.5], min=0.2),
                    pb.ParameterSpec(key=HIDDEN, initial_value=[0.3])]))


def test_a_job_ends_with_each_verdict_through_the_api(three):
    done, result = three
    values = {p.key: p for p in result.parameters}
    seen, dark, hidden = values[SEEN], values[AT_BOUND], values[HIDDEN]
    assert list(seen.interval) == [pb.INTERVAL_TWO_SIDED] * 3, seen
    assert all(0 < e < 0.1 for e in seen.standard_error), seen
    assert list(dark.interval) == [pb.INTERVAL_AT_LOWER_BOUND], dark
    assert dark.value[0] == pytest.approx(0.2, abs=1e-6) and 0 < dark.standard_error[0] < 0.15
    assert list(hidden.interval) == [pb.INTERVAL_NOT_DETERMINED], hidden
    assert math.isinf(hidden.standard_error[0])
    assert list(hidden.interval_reason) == ["the render does not change with it"]
    # Only a component not determined has a reason.
    assert not seen.interval_reason and not dark.interval_reason
    # The notes agree: none gives the hidden colour an interval.
    about = [n for n in done.notes if HIDDEN in n]
    assert about and all("+-" not in n and "within" not in n for n in about), about
    # The job's status shows the best result's verdicts as they are.
    shown = {p.key: p for p in done.best_parameters}
    assert list(shown[HIDDEN].interval_reason) == list(hidden.interval_reason)
    assert list(shown[AT_BOUND].interval) == list(dark.interval)


def test_the_cli_and_the_csv_export_show_the_same_verdicts(three, cli_env, tmp_path):
    done, _ = three

    def matopt(*args: str) -> str:
        out = subprocess.run([sys.executable, "-m", "matopt_client.cli", *args], env=cli_env,
                             capture_output=True, text=True, timeout=120, check=False)
        assert out.returncode == 0, out.stderr
        return out.stdout

    text = matopt("job", "result", done.name)
    line = {x.split(":", 1)[0]: x.split(":", 1)[1] for x in text.splitlines() if ":" in x}
    assert "+-" in line[SEEN] and line[SEEN].count("+-") == 3
    assert "(at its bound, +" in line[AT_BOUND]
    assert line[HIDDEN].strip().endswith(
        "(not determined by these images: the render does not change with it)")
    assert "+-" not in line[HIDDEN]
    status = matopt("job", "status", done.name)
    assert "not determined by these images: the render does not change with it" in status
    document = json.loads(matopt("job", "result", done.name, "--json"))
    hidden = next(p for p in document["parameters"] if p["key"] == HIDDEN)
    assert hidden["interval"] == ["INTERVAL_NOT_DETERMINED"]
    assert hidden["intervalReason"] == ["the render does not change with it"]
    matopt("job", "export", done.name, "--out", str(tmp_path / "out"))
    with open(tmp_path / "out" / "parameters.csv") as f:
        rows = {(r["parameter"], int(r["component"])): r for r in csv.DictReader(f)}
    assert [rows[(SEEN, c)]["interval"] for c in range(3)] == ["two_sided"] * 3
    assert rows[(AT_BOUND, 0)]["interval"] == "at_lower_bound"
    assert rows[(HIDDEN, 0)]["interval"] == "not_determined"
    assert rows[(HIDDEN, 0)]["standard_error"] == "inf"
    assert rows[(HIDDEN, 0)]["reason"] == "the render does not change with it"
    assert rows[(SEEN, 0)]["reason"] == ""
    exported = json.loads((tmp_path / "out" / "parameters.json").read_text())
    assert exported["standard_errors"][HIDDEN] == [None]
    assert exported["reasons"] == {HIDDEN: ["the render does not change with it"]}


# -- reconciling the two judges (no renderer) ---------------------------------------------------

@pytest.fixture(scope="module")
def engine():
    """The engine's modules in this process (uncertainty.py loads Mitsuba's integrators)."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("llvm_ad_rgb")


def _estimate():
    from matoptd import engine_api as api
    from matoptd.engine.uncertainty import Estimate
    errors = {"glass.roughness": api.StandardError(np.array([0.0092], np.float32),
                                                   ["two_sided"]),
              "glass.spec_trans": api.StandardError(np.array([0.22], np.float32),
                                                    ["at_lower_bound"]),
              "glass.eta": api.StandardError(np.array([0.039], np.float32), ["two_sided"])}
    about = {"glass.spec_trans": [("glass.spec_trans: ended at a bound 0, so its interval is "
                                   "one-sided: the truth lies within +0.45 of it")],
             "quad.base_color.data": ["quad.base_color.data: its mean level is known to +- 0.01"]}
    return Estimate(errors, {}, ["glass.eta and quad.base_color.data (mean level) trade off"],
                    about=about)


def test_what_the_history_finds_undecided_loses_its_interval(engine):
    """The held-out case: the notes said roughness and spec_trans were not decided while the
    result gave roughness 0.1318 +- 0.0092 and spec_trans a one-sided interval. Reconciled,
    both are not determined, with the diagnosis's reason, and the notes that gave them an
    interval are gone; eta, which nothing found undecided, keeps its interval."""
    from matoptd.engine import diagnosis, verdicts
    drift = "it drifted on gradients of no consistent sign"
    out = verdicts.reconcile(_estimate(), diagnosis.Diagnosis(
        [], {"glass.roughness": drift,
             "glass.spec_trans": "it trades off with glass.roughness at a level loss"}), {})
    rough, spec, eta = (out.errors[k] for k in ("glass.roughness", "glass.spec_trans",
                                                "glass.eta"))
    assert rough.reading == ["not_determined"] and np.isinf(rough.error).all()
    assert rough.reason == [drift]
    assert spec.reading == ["not_determined"] and spec.reason[0].startswith("it trades off")
    assert eta.reading == ["two_sided"] and eta.error[0] == pytest.approx(0.039)
    assert not any("within +0.45" in n for n in out.notes)
    assert any("mean level is known" in n for n in out.notes)  # untouched


def test_a_wander_widens_the_interval_to_span_it(engine):
    """Drifting on gradients of no consistent sign, or two values wandering in step at a
    level loss, says the images did not steer them: the result's interval spans that
    scatter (the standard error at least the wander over four), and the note says so; where
    that interval would be too wide to say anything (the wander's limit), or for either of
    a pair, neither is determined."""
    from matoptd.engine import diagnosis, verdicts
    note = "glass.roughness drifted (0.13 -> 0.14 over its last 20 iterations) on noise"
    within = "glass.roughness drifted by ...: its interval is at least as wide"
    why = "it drifted on gradients of no consistent sign"

    def judged(moved: float, limit: float = np.inf) -> verdicts.Verdicts:
        return verdicts.reconcile(_estimate(), diagnosis.Diagnosis(
            [note], {"glass.roughness": why},
            {"glass.roughness": diagnosis.Wander(np.array([moved]), note, within, limit)}), {})

    covered = judged(0.015)  # standard error 0.0092: its interval spans the wander already
    assert covered.errors["glass.roughness"].reading == ["two_sided"]
    assert covered.errors["glass.roughness"].error[0] == pytest.approx(0.0092)
    assert note not in covered.notes and within in covered.notes
    wider = judged(0.05)
    assert wider.errors["glass.roughness"].reading == ["two_sided"]
    assert wider.errors["glass.roughness"].error[0] == pytest.approx(0.0125)
    assert within in wider.notes
    beyond = judged(0.05, limit=0.01)
    assert beyond.errors["glass.roughness"].reading == ["not_determined"]
    assert beyond.errors["glass.roughness"].reason == [why] and note in beyond.notes

    pair = "glass.roughness and glass.eta trade off"
    both = "glass.roughness and glass.eta wandered in step"

    def paired(eta_moved: float) -> verdicts.Verdicts:
        return verdicts.reconcile(_estimate(), diagnosis.Diagnosis(
            [pair], {"glass.roughness": "it trades off with glass.eta at a level loss",
                     "glass.eta": "it trades off with glass.roughness at a level loss"},
            {"glass.roughness": diagnosis.Wander(np.array([0.01]), pair, both, 0.1),
             "glass.eta": diagnosis.Wander(np.array([eta_moved]), pair, both, 0.1)}), {})

    assert paired(0.15).errors["glass.eta"].reading == ["two_sided"]  # 4 x 0.039
    assert paired(0.3).errors["glass.eta"].error[0] == pytest.approx(0.075)
    assert paired(0.3).notes[0] == both
    split = paired(0.5)  # 0.125 > its limit
    assert [split.errors[k].reading for k in ("glass.roughness", "glass.eta")] == [
        ["not_determined"], ["not_determined"]]
    assert split.notes[0] == pair


def test_the_widest_interval_that_says_something():
    """A quarter of the range; in log space of the log-range times the value; unbounded, a
    quarter of the value (log) or 0.25 (linear)."""
    from matoptd.engine.diagnosis import Kept, widest
    assert widest(Kept(0.0, 1.0), np.array([0.5, 0.9])) == pytest.approx([0.25, 0.25])
    assert widest(Kept(0.0, np.inf, log=True), np.array([2.0])) == pytest.approx([0.5])
    assert widest(Kept(0.0, 1.0, 0.001, True), np.array([0.3])) == pytest.approx(
        [0.25 * np.log(1000) * 0.3])


def test_an_undecided_value_without_a_standard_error_still_gets_its_verdict(engine):
    """No estimate (too many components, or it failed): a value the diagnosis finds
    undecided is not determined all the same; a texture's mean-level note goes."""
    from matoptd.engine import diagnosis, verdicts
    from matoptd.engine.uncertainty import Estimate
    about = {"quad.base_color.data": ["quad.base_color.data: its mean level is known to +- 0.01"]}
    out = verdicts.reconcile(Estimate({}, {}, [], about=about), diagnosis.Diagnosis(
        [], {"obj.albedo": "it never moved", "quad.base_color.data": "it never moved"}),
        {"obj.albedo": 3})
    assert out.errors["obj.albedo"].reading == ["not_determined"] * 3
    assert out.errors["obj.albedo"].reason == ["it never moved"] * 3
    assert "quad.base_color.data" not in out.errors and not out.notes


def test_the_diagnosis_names_what_it_finds_undecided():
    from matoptd.engine.diagnosis import undecided
    n = 100
    losses = list(0.001 + 1e-5 * np.random.default_rng(1).standard_normal(n))
    losses[:3] = [0.1] * 3  # it fell, then stayed level
    found = undecided(losses, {"obj.eta": np.full((n, 1), 1.5)}, {})
    assert found.undecided == {"obj.eta": "it never moved: the images carry no gradient for it"}
    assert "obj.eta hardly moved" in found.notes[0]
    # Found not determined by the standard errors already: no second note, no second reason.
    assert not undecided(losses, {"obj.eta": np.full((n, 1), 1.5)}, {}, set(),
                         {"obj.eta"}).undecided


# -- a texture that can stand in for a scalar ---------------------------------------------------

LAMP = "lamp.intensity.value"
TEXTURE = "quad.bsdf.reflectance.data"


def lamp_on_a_textured_quad(res: int = RES) -> str:
    """A textured quad under a white environment and a point light off to its left: the light
    adds a falloff from left to right, which a texture brighter on its left can mimic."""
    return textured_quad(res, filename="albedo.exr", lights=(
        '<emitter type="point" id="lamp"><point name="position" value="-2.5, 0, 1"/>'
        '<float name="intensity" value="4"/></emitter>'))


def test_a_texture_that_can_stand_in_for_a_light_widens_its_interval(stubs):
    """The light's intensity, alone, is pinned by the falloff it adds. Optimized beside the
    texture, whose left-right ramp enters J, the same images leave it far less sure: the
    standard error grows (or the intensity is not determined at all)."""
    texels = np.full((4, 4, 3), 0.5, dtype=np.float32)
    texels[::2, ::2] = 0.3  # a pattern, so that the texture is not a flat colour
    scene = create_scene(stubs, {"lamp.xml": lamp_on_a_textured_quad().encode(),
                                 "albedo.exr": exr(texels)}, "lamp.xml")
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=128)).images[0]

    def lamp(*extra: pb.ParameterSpec) -> pb.ParameterValue:
        done, result = finished(stubs, pb.JobSpec(
            scene=scene.name, references=[pb.Reference(blob=ref.exr_blob)], iterations=30,
            spp=8, parameters=[pb.ParameterSpec(key=LAMP, initial_value=[3.0] * 3), *extra]))
        return next(p for p in result.parameters if p.key == LAMP), done.notes

    alone, _ = lamp()
    assert list(alone.interval) == [pb.INTERVAL_TWO_SIDED] * 3, alone
    beside, notes = lamp(pb.ParameterSpec(key=TEXTURE))
    # With the texture's mean level alone in J it was 3.6 times as wide (3.05 +- 0.56, truth
    # 4); with its ramps, 11 times: more than a quarter of its value, so not determined.
    for c in range(3):
        assert (beside.interval[c] == pb.INTERVAL_NOT_DETERMINED
                or beside.standard_error[c] > 6 * alone.standard_error[c]), (alone, beside)
    # The ramps entered J: the lamp's 3 components and the texture's mean level and 2 ramps
    # per channel (its own note may then go with a verdict of not determined).
    assert any(n.startswith("standard errors: 12 components") for n in notes), notes
