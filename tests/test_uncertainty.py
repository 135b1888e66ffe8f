"""Standard errors of recovered values, without ground truth, through a real daemon: each
result value comes with one per component, read as its interval says; what the images do not
decide is said, never NaN; a gain is estimated with the parameters; a texture gets its mean
level. The calibration (does the truth lie within two standard errors as often as it should)
is tests/test_calibration.py."""

from __future__ import annotations

import math

import grpc
import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import finished as run, wait_iteration, wait_state
from scenes import camera, create_scene, glass_with_medium, upload, vol

RES = 24
WALLS = {"red.reflectance.value": [0.570068, 0.0430135, 0.0443706],
         "green.reflectance.value": [0.105421, 0.37798, 0.076425]}
LIGHT = "light.emitter.radiance.value"


@pytest.fixture(scope="module")
def cornell(stubs):
    """The built-in Cornell box at RES px and a 256-spp render of it (EXR blob)."""
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(
        overrides={"resx": str(RES), "resy": str(RES)}))
    image = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=256)).images[0]
    return scene, image.exr_blob


@pytest.fixture(scope="module")
def walls(stubs, cornell) -> tuple[pb.Job, pb.JobResult]:
    """A finished job on the Cornell box's red and green walls, from grey."""
    scene, reference = cornell
    return run(stubs, pb.JobSpec(
        scene=scene.name, references=[pb.Reference(blob=reference)], iterations=40, spp=8,
        parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3) for k in WALLS]))


def test_each_wall_colour_comes_with_a_standard_error(walls):
    done, result = walls
    for p in result.parameters:
        assert len(p.standard_error) == len(p.value) == 3, p
        # A dark channel (truth 0.04) may end on the range's bound 0 at this size: then its
        # interval is one-sided, above the bound.
        assert list(p.interval) == [pb.INTERVAL_AT_LOWER_BOUND if v == 0 else
                                    pb.INTERVAL_TWO_SIDED for v in p.value], p
        # A 24 px view at 8 spp pins a wall's colour to a few percent, not to 1e-5 or 0.3.
        assert all(1e-3 < e < 0.1 for e in p.standard_error), p
    # GetJob shows the best result's values with the same standard errors.
    shown = {p.key: p for p in done.best_parameters}
    assert set(shown) == set(WALLS)
    for p in result.parameters:
        assert list(shown[p.key].standard_error) == list(p.standard_error)


def test_a_paused_job_estimates_its_standard_errors_on_request(stubs, cornell, walls):
    """Half-way, how sure are the values? A running job is told to pause first; a paused one
    gets for its kept iteration the standard errors an end would give, and then goes on as
    it would have."""
    scene, reference = cornell
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, references=[pb.Reference(blob=reference)], iterations=100_000, spp=8,
        parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3) for k in WALLS])))
    wait_iteration(stubs, job.name, 40)
    asking = pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST,
                                    estimate_standard_errors=True)
    with pytest.raises(grpc.RpcError) as err:
        stubs.jobs.GetJobResult(asking)
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION
    assert "pause it first" in err.value.details()
    stubs.jobs.PauseJob(pb.PauseJobRequest(name=job.name))
    at = wait_state(stubs, job.name, (pb.JOB_STATE_PAUSED,)).iteration
    plain = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST))
    assert all(not p.standard_error for p in plain.parameters)
    asked = stubs.jobs.GetJobResult(asking)
    assert asked.iteration == plain.iteration == at - 1
    ended = {p.key: p for p in walls[1].parameters}
    for p, q in zip(asked.parameters, plain.parameters):
        assert list(p.value) == list(q.value)
        assert len(p.standard_error) == 3, p
        # about what the same job ended with at 40 iterations (another draw of its noise)
        for e, reading, other in zip(p.standard_error, p.interval,
                                     ended[p.key].standard_error):
            assert reading != pb.INTERVAL_NOT_DETERMINED and other / 4 < e < 4 * other, p
    assert any(n.startswith("standard errors: 6 components") for n in asked.standard_error_notes)
    stubs.jobs.ResumeJob(pb.ResumeJobRequest(name=job.name))
    assert wait_iteration(stubs, job.name, at + 3).resumed_from == f"checkpoint at iteration {at}"
    stubs.jobs.CancelJob(pb.CancelJobRequest(name=job.name))


def test_a_paused_jobs_estimate_beside_a_loaded_glass_job(stubs, cornell, walls):
    """The estimate loads on a worker where another user's glass job is loaded and stepping.
    Mitsuba dispatches a BSDF's call over every live instance, the glass's too: the
    estimate's forward-mode passes must not meet the AD edges that job's scene holds."""
    scene, reference = cornell
    paused = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, references=[pb.Reference(blob=reference)], iterations=100_000, spp=8,
        parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3) for k in WALLS])))
    wait_iteration(stubs, paused.name, 10)
    stubs.jobs.PauseJob(pb.PauseJobRequest(name=paused.name))
    wait_state(stubs, paused.name, (pb.JOB_STATE_PAUSED,))
    glass = create_scene(stubs, {"glass.xml": glass_with_medium(16).encode()}, "glass.xml")
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=glass.name, spp=16)).images[0]
    loaded = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=glass.name, references=[pb.Reference(blob=ref.exr_blob)], iterations=100_000,
        spp=2, parameters=[pb.ParameterSpec(key="blob.bsdf.eta", initial_value=[1.4])])))
    wait_iteration(stubs, loaded.name, 3)
    asked = stubs.jobs.GetJobResult(pb.GetJobResultRequest(
        name=paused.name, which=pb.WHICH_LAST, estimate_standard_errors=True))
    assert stubs.jobs.GetJob(pb.GetJobRequest(name=loaded.name)).state == pb.JOB_STATE_RUNNING
    for p in asked.parameters:
        assert len(p.standard_error) == 3 and pb.INTERVAL_NOT_DETERMINED not in p.interval, asked.standard_error_notes
    assert not any("fail" in n for n in asked.standard_error_notes), asked.standard_error_notes
    for job in (paused, loaded):
        stubs.jobs.CancelJob(pb.CancelJobRequest(name=job.name))


def test_a_light_and_a_gain_that_only_scale_together_are_not_determined(stubs, cornell):
    """With fit_exposure, the light's radiance and the gain scale the same image: only their
    product is decided. Both are said to be not determined (+inf, never NaN), by name, while
    a wall's colour, which changes the image's pattern, keeps a finite standard error."""
    scene, reference = cornell
    done, result = run(stubs, pb.JobSpec(
        scene=scene.name, references=[pb.Reference(blob=reference, filename="box.exr")],
        iterations=30, spp=8, fit_exposure=True,
        parameters=[pb.ParameterSpec(key=LIGHT),
                    pb.ParameterSpec(key="red.reflectance.value", initial_value=[0.5] * 3)]))
    values = {p.key: p for p in result.parameters}
    light = values[LIGHT]
    assert list(light.interval) == [pb.INTERVAL_NOT_DETERMINED] * 3
    assert all(math.isinf(e) and e > 0 for e in light.standard_error)
    [gain] = result.gains
    assert list(gain.interval) == [pb.INTERVAL_NOT_DETERMINED] * 3
    red = values["red.reflectance.value"]
    assert all(np.isfinite(red.standard_error)) and not any(np.isnan(red.standard_error))
    note = next(n for n in done.notes if n.startswith("not determined by these images"))
    assert LIGHT in note and "gain of box.exr" in note


def thin_cloud(res: int = 32) -> str:
    """A thin homogeneous medium with a 4^3 RGB albedo grid, lit by a point light against
    black: the light it scatters grows with albedo times sigma_t, and only its attenuation,
    faint at sigma_t 0.3, tells the two apart."""
    return f"""<scene version="3.0.0">
    <integrator type="volpath"><integer name="max_depth" value="8"/></integrator>
    {camera(res, "0, 0.5, 4")}
    <emitter type="point" id="lamp"><point name="position" value="3, 3, 3"/>
        <rgb name="intensity" value="60"/></emitter>
    <shape type="sphere" id="cloud">
        <bsdf type="null"/>
        <medium type="homogeneous" name="interior">
            <volume type="gridvolume" name="albedo"><string name="filename" value="albedo.vol"/>
            </volume>
            <float name="sigma_t" value="0.3"/>
        </medium>
    </shape>
</scene>
"""


def test_a_grid_albedo_and_sigma_t_are_named_together(stubs):
    """A medium's albedo grid (192 values, past the 64 the history's trade-off check reads)
    against its sigma_t: the notes name the grid's mean level and sigma_t together, as a pair
    that trades off or as components the images do not tell apart, and give the grid's mean
    level a standard error per channel (or say which channels have none)."""
    import thesis_scenes as ts

    grid_values = ts.albedo_grid(4)
    scene = create_scene(stubs, {"cloud.xml": thin_cloud().encode(),
                                 "albedo.vol": vol(grid_values, -1, 1)}, "cloud.xml")
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=64,
                                                         sensors=[0], seed=3)).images[0]
    grid, sigma_t = "cloud.interior_medium.albedo.data", "cloud.interior_medium.sigma_t.value.value"
    done, result = run(stubs, pb.JobSpec(
        scene=scene.name, references=[pb.Reference(blob=ref.exr_blob)], iterations=120,
        parameters=[pb.ParameterSpec(key=grid, initial_blob=_npy_blob(stubs, grid_values)),
                    pb.ParameterSpec(key=sigma_t, initial_value=[0.3])]))
    assert any(n.startswith(f"{grid}: its mean level is known to +-") for n in done.notes)
    together = [n for n in done.notes if f"{grid} (mean level" in n and sigma_t in n]
    assert together and ("trade off" in together[0] or "change the render as one"
                         in together[0]), done.notes
    values = {p.key: p for p in result.parameters}
    assert not values[grid].standard_error and values[grid].blob
    assert len(values[sigma_t].standard_error) == len(values[sigma_t].interval) == 1


def _npy_blob(stubs, array) -> str:
    import io
    buf = io.BytesIO()
    np.save(buf, np.asarray(array, dtype=np.float32))
    return f"blobs/{upload(stubs, buf.getvalue())}"


def test_the_cli_and_the_export_show_each_value_with_its_standard_error(walls, cli_env,
                                                                        tmp_path):
    import csv
    import json
    import subprocess
    import sys

    done, result = walls

    def matopt(*args: str) -> str:
        out = subprocess.run([sys.executable, "-m", "matopt_client.cli", *args], env=cli_env,
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        return out.stdout

    red = next(p for p in result.parameters if p.key == "red.reflectance.value")
    shown = matopt("job", "result", done.name)
    line = next(x for x in shown.splitlines() if x.startswith("red.reflectance.value:"))
    first = line.split(":", 1)[1].split(",")[0].split()
    assert first[1] == "+-" and float(first[2]) == pytest.approx(red.standard_error[0], rel=0.06)
    status = matopt("job", "status", done.name)
    assert "best result:" in status and "+-" in status
    document = json.loads(matopt("job", "result", done.name, "--json"))
    red_json = next(p for p in document["parameters"] if p["key"] == red.key)
    assert red_json["standardError"] == pytest.approx(list(red.standard_error))
    matopt("job", "export", done.name, "--out", str(tmp_path / "out"))
    exported = json.loads((tmp_path / "out" / "parameters.json").read_text())
    assert exported["standard_errors"][red.key] == pytest.approx(list(red.standard_error),
                                                                 rel=1e-3)
    rows = list(csv.DictReader(open(tmp_path / "out" / "parameters.csv")))
    assert {(r["parameter"], int(r["component"])) for r in rows} == {
        (k, i) for k in WALLS for i in range(3)}
    assert all(r["interval"] in ("two_sided", "at_lower_bound") for r in rows)
