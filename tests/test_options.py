"""Job options beyond the defaults: every loss, per-sensor steps, clamping, legacy scenes."""

from __future__ import annotations

import math

import pytest

from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb

from conftest import wait_state
from scenes import create_scene

WALL = "red.reflectance.value"
TRUTH = [0.570068, 0.0430135, 0.0443706]


@pytest.fixture(scope="module")
def box(stubs):
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "32",
                                                                      "resy": "32"}))
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=256)).images[0]
    return scene, ref


def run(stubs, scene, refs, iterations=80, **spec) -> tuple[pb.Job, list[float]]:
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=iterations, min_error=-1, references=refs,
        parameters=[pb.ParameterSpec(key=WALL, initial_value=[0.3, 0.3, 0.3])], **spec)))
    done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
    assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
    last = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST))
    return done, list(last.parameters[0].value)


@pytest.mark.parametrize("loss", [pb.LOSS_MSE, pb.LOSS_DUAL_BUFFER, pb.LOSS_MAE, pb.LOSS_MULTISCALE_MSE])
def test_every_objective_recovers_the_wall(stubs, box, loss):
    scene, ref = box
    done, got = run(stubs, scene, [pb.Reference(blob=ref.exr_blob)], loss=loss)
    assert got == pytest.approx(TRUTH, abs=0.05), enums.short_name(pb.Loss, loss)


def test_a_sample_count_schedule_renders_each_phase_at_its_spp_and_records_it(stubs, box):
    """--spp 1 --spp-from 2:256 --spp-from 4:4: the parameters barely move (a tiny rate), so
    the loss is the render noise's, which falls with spp: the 256-spp phase's is far lower."""
    scene, ref = box
    done, _ = run(stubs, scene, [pb.Reference(blob=ref.exr_blob)], iterations=5, spp=1,
                  spp_from={2: 256, 4: 4}, learning_rate=1e-6)
    assert dict(done.spec.spp_from) == {2: 256, 4: 4}
    history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=done.name)).iterations
    assert [r.spp for r in history] == [1, 1, 256, 256, 4]
    loss = [r.loss for r in history]
    assert max(loss[2:4]) < min(loss[:2]) / 4 and max(loss[2:4]) < loss[4], loss


def test_brightness_independent_mse_recovers_colour_against_a_lit_background(stubs):
    """Normalizing by the image mean keeps the object's colour relative to what surrounds it.
    (In the Cornell box the light's pixels, ~18 at 4 spp, dominate that mean and its noise.)"""
    two = create_scene(stubs, {"two.xml": TWO_CAMERAS.encode()}, "two.xml")
    refs = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=two.name, spp=128)).images
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=two.name, iterations=80, min_error=-1, loss=pb.LOSS_BRIGHTNESS_INDEPENDENT_MSE,
        references=[pb.Reference(blob=i.exr_blob) for i in refs],
        parameters=[pb.ParameterSpec(key="ball.bsdf.reflectance.value",
                                     initial_value=[0.5, 0.5, 0.5])])))
    wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED,))
    last = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST))
    assert list(last.parameters[0].value) == pytest.approx([0.2, 0.6, 0.3], abs=0.06)


def test_brightness_independent_loss_is_safe_on_black_images(stubs, box):
    scene, ref = box
    black = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=1, parameters=[
        pb.ParameterValue(key="light.emitter.radiance.value", value=[0, 0, 0])])).images[0]
    done, got = run(stubs, scene, [pb.Reference(blob=black.exr_blob)], iterations=5,
                    loss=pb.LOSS_BRIGHTNESS_INDEPENDENT_MSE)
    history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=done.name)).iterations
    assert all(math.isfinite(r.loss) for r in history)
    assert all(math.isfinite(v) for v in got) and done.skipped_steps == 0


def test_step_per_sensor_takes_a_step_per_camera_and_accumulate_one(stubs):
    """Two cameras: one accumulated Adam step per iteration, or one step per sensor (thesis);
    both recover the colour. Adam's first step moves each component by its learning rate whatever the gradient's size,
    so from theta_0 to theta_1 accumulate moves by lr and step-per-sensor by about 2 lr."""
    lr = 0.05
    two = create_scene(stubs, {"two.xml": TWO_CAMERAS.encode()}, "two.xml")
    refs = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=two.name, spp=128)).images
    first_move = {}
    for mode in (pb.SENSOR_MODE_ACCUMULATE, pb.SENSOR_MODE_STEP_PER_SENSOR):
        job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
            scene=two.name, iterations=60, min_error=0, sensor_mode=mode, learning_rate=lr,
            references=[pb.Reference(blob=i.exr_blob) for i in refs],
            parameters=[pb.ParameterSpec(key="ball.bsdf.reflectance.value",
                                         initial_value=[0.5, 0.5, 0.5])])))
        done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
        assert done.state == pb.JOB_STATE_SUCCEEDED and list(done.sensors_rendered) == [0, 1]
        assert done.spec.sensor_mode == mode
        last = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST))
        assert list(last.parameters[0].value) == pytest.approx([0.2, 0.6, 0.3], abs=0.05)
        history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=job.name)).iterations
        theta0, theta1 = (list(history[i].parameters[0].value) for i in (0, 1))
        assert theta0 == pytest.approx([0.5, 0.5, 0.5])
        first_move[mode] = [abs(b - a) for a, b in zip(theta0, theta1)]
    assert first_move[pb.SENSOR_MODE_ACCUMULATE] == pytest.approx([lr] * 3, rel=0.02)
    # The second step's size depends on how the two gradients compare (about 0.9 lr here:
    # both views see the same sphere); accumulate's one step is lr.
    assert all(1.5 * lr < m < 2.02 * lr for m in first_move[pb.SENSOR_MODE_STEP_PER_SENSOR]), \
        first_move


SKY = """<scene version="3.0.0">
    <sensor type="perspective">
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
    </sensor>
    <emitter type="constant"><rgb name="radiance" value="4"/></emitter>
</scene>
"""


def test_clamp_is_off_unless_asked(stubs):
    """An HDR reference (a sky of radiance 4): unclamped, the radiance is recovered; clamped to
    [0, 1] both images saturate, the gradient vanishes, and the radiance stays put."""
    scene = create_scene(stubs, {"sky.xml": SKY.encode()}, "sky.xml")
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=4)).images[0]
    key = "emitter_0.radiance.value"
    results = {}
    for clamp in (False, True):
        job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
            scene=scene.name, iterations=60, min_error=-1, clamp=clamp,
            references=[pb.Reference(blob=ref.exr_blob)],
            parameters=[pb.ParameterSpec(key=key, initial_value=[2, 2, 2])])))
        wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED,))
        results[clamp] = list(stubs.jobs.GetJobResult(pb.GetJobResultRequest(
            name=job.name, which=pb.WHICH_LAST)).parameters[0].value)
    assert results[False] == pytest.approx([4, 4, 4], rel=0.05)
    assert results[True] == pytest.approx([2, 2, 2], rel=1e-6)


LEGACY = """<scene version="3.0.0">
    <default name="integrator" value="prb_reparam"/>
    <integrator type="$integrator">
        <integer name="max_depth" value="3"/>
        <integer name="reparam_rays" value="16"/>
    </integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
    </sensor>
    <emitter type="constant"/>
    <shape type="sphere"><bsdf type="diffuse"/></shape>
</scene>
"""

TWO_CAMERAS = """<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="3"/></integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="24"/></film>
    </sensor>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="3, 0, 0" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="16"/></film>
    </sensor>
    <emitter type="constant"/>
    <shape type="sphere" id="ball"><bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.6, 0.3"/></bsdf></shape>
</scene>
"""


def test_legacy_reparam_scene_loads_with_a_warning(stubs):
    scene = create_scene(stubs, {"old.xml": LEGACY.encode()}, "old.xml")
    assert any("prb_reparam" in w and "prb_projective" in w for w in scene.warnings)
    assert any("reparam_rays" in w for w in scene.warnings)
    # and it renders
    image = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=4)).images[0]
    assert (image.width, image.height) == (16, 16)
