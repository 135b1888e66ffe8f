"""Frozen iterations (engine/choices/frozen.py, engine/frozen.py) in-process: a job run frozen
follows the same trajectory as the same job unfrozen, for surfaces, textures (through a
multires level change), media, several sensors, a spp schedule, a checkpoint in between and
two jobs stepped in turn; it records again only when the structure changes, and says so; and
it falls back, saying why, where a job cannot be frozen. A job with eta by differences runs
frozen too, and the standard errors' passes follow the choice."""

from __future__ import annotations

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from matopt_api.v1 import matopt_pb2 as pb  # noqa: E402
from matoptd import settings as api  # noqa: E402

from conftest import wait_state  # noqa: E402
from scenes import cornell_with_truth  # noqa: E402

RED = "red.reflectance.value"
GREEN = "green.reflectance.value"
TEXTURE = "quad.bsdf.reflectance.data"
GRID = "box.interior_medium.albedo.data"
ALBEDO = "ball.interior_medium.albedo.value.value"
ETA = "ball.bsdf.eta"
RANGES = {ETA: (1.0, 2.0)}


@pytest.fixture(scope="module")
def optimize():
    mi.set_variant("llvm_ad_rgb")
    from matoptd.engine import optimize
    return optimize


def _cornell(sensors: int = 1, block: bool = False):
    scene = mi.cornell_box()
    if block:  # a mesh of its own id, for its vertex positions
        scene["block"] = {"type": "cube", "to_world": mi.ScalarTransform4f().scale(0.2),
                          "bsdf": {"type": "diffuse"}}
    scene["sensor"]["film"]["width"] = scene["sensor"]["film"]["height"] = 16
    scene["integrator"]["max_depth"] = 3
    for k in range(1, sensors):
        scene[f"sensor{k}"] = dict(scene["sensor"], to_world=mi.ScalarTransform4f().look_at(
            origin=[0.6 * k, 0.2, 3.9], target=[0, 0, 0], up=[0, 1, 0]))
    return mi.load_dict(scene)


def _lit(integrator: str, depth: int, origin: list[float], **shapes) -> mi.Scene:
    """``shapes`` under a white environment, seen by a 16 px camera from ``origin``."""
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": depth},
        "sensor": {"type": "perspective", "fov": 32, "to_world": mi.ScalarTransform4f().look_at(
            origin=origin, target=[0, 0, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
        "light": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}, **shapes})


def _quad():
    """A textured quad (16x16 float texture)."""
    texels = np.random.default_rng(3).uniform(0.2, 0.8, (16, 16, 3)).astype(np.float32)
    return _lit("prb", 3, [0, 0, 4], quad={"type": "rectangle", "bsdf": {
        "type": "diffuse", "reflectance": {"type": "bitmap", "filter_type": "nearest",
                                           "bitmap": mi.Bitmap(texels)}}})


def _medium():
    """A ball of homogeneous medium (prbvolpath)."""
    fog = {"type": "homogeneous", "sigma_t": 2.0,
           "albedo": {"type": "rgb", "value": [0.8, 0.5, 0.3]}}
    return _lit("volpath", 6, [0, 0, 4],
                ball={"type": "sphere", "bsdf": {"type": "null"}, "interior": fog})


def _grid():
    """A cube of heterogeneous medium whose albedo is an 8x8x8 RGB grid."""
    voxels = np.random.default_rng(5).uniform(0.2, 0.8, (8, 8, 8, 3)).astype(np.float32)
    return _lit("volpath", 4, [2, 1.5, 3.5], box={
        "type": "cube", "to_world": mi.ScalarTransform4f().scale(0.8), "bsdf": {"type": "null"},
        "interior": {"type": "heterogeneous", "sigma_t": 1.5, "albedo": {
            "type": "gridvolume", "filter_type": "nearest", "grid": mi.VolumeGrid(voxels)}}})


def _glass(alpha: float = 0.01):
    """A rough glass ball (alpha 0.01: eta by differences) in front of a checkered backdrop."""
    backdrop = np.indices((8, 8)).sum(axis=0) % 2 * 0.6 + 0.2
    return _lit("prb", 4, [0, 0, 4], ball={
        "type": "sphere", "radius": 0.7, "bsdf": {"type": "roughdielectric", "alpha": alpha,
                                                 "int_ior": 1.5}},
        wall={"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -1.5])
              @ mi.ScalarTransform4f().scale(2.0), "bsdf": {"type": "diffuse", "reflectance": {
                  "type": "bitmap", "filter_type": "nearest", "bitmap": mi.Bitmap(
                      np.repeat(backdrop[..., None], 3, axis=2).astype(np.float32))}}})


def _settings(keys, iterations: int = 8, spp_from=None, fit_exposure: bool = False,
              sensor_mode: str = "accumulate", **choices: str) -> api.JobSettings:
    return api.JobSettings(api.SceneInput("k", "s.xml", {}, {}, "s.xml"), [],
                           [api.ParameterSetting(k, 0.05, *RANGES.get(k, (0.0, 1.0)))
                            for k in keys],
                           iterations=iterations, spp=4, choices=choices,
                           spp_from=spp_from or {}, fit_exposure=fit_exposure,
                           sensor_mode=sensor_mode)


def _references(optimize, scene) -> dict:
    return {n: optimize.Reference(mi.TensorXf(np.asarray(
        mi.render(scene, sensor=n, spp=16, seed=99))[..., :3]), None, f"ref{n}")
        for n in range(len(scene.sensors()))}


def _start(make, keys) -> dict[str, np.ndarray]:
    """Each parameter moved away from the scene's value (what the job starts from)."""
    params = mi.traverse(make())
    return {k: np.asarray(params[k]).ravel() * 1.06 if k in RANGES else
            np.clip(np.asarray(params[k]).ravel() * 0.5 + 0.1, 0, 1) for k in keys}


class Job:
    """A job's loop on a fresh scene, its references rendered from the scene as loaded."""

    def __init__(self, optimize, make, settings, checkpoint=None, moved: bool = True) -> None:
        scene = make()
        keys = [p.key for p in settings.parameters]
        self.loop = optimize.Optimization(scene, settings, _references(optimize, scene),
                                          checkpoint=checkpoint,
                                          initial=_start(make, keys) if moved else None)
        self.steps = []

    def run(self, n: int) -> Job:
        for _ in range(n):
            self.steps.append(self.loop.step())
        return self


def _same(a: list, b: list) -> None:
    """Two trajectories agree within float noise: losses and every value at every step."""
    assert [s.iteration for s in a] == [s.iteration for s in b]
    np.testing.assert_allclose([s.loss for s in a], [s.loss for s in b], rtol=1e-4)
    for x, y in zip(a, b):
        for key in x.values:
            np.testing.assert_allclose(x.values[key], y.values[key], rtol=1e-4, atol=1e-6)


def _why(loop) -> str:
    return next(c.why for c in loop.choices if c.name == "frozen")


@pytest.mark.parametrize("make, keys, extra", [
    (_cornell, [RED, GREEN], {}),
    (_quad, [TEXTURE], {}),               # multires: 4x4 -> 8x8 -> 16x16 during the job
    (_medium, [ALBEDO], {}),
    (_grid, [GRID], {}),
    (lambda: _cornell(2), [RED, GREEN], {}),
    (lambda: _cornell(2), [RED, GREEN], {"sensor_mode": "step_per_sensor"}),
], ids=["surface", "texture", "medium", "grid", "two_sensors", "step_per_sensor"])
def test_frozen_follows_the_unfrozen_trajectory(optimize, make, keys, extra):
    frozen = Job(optimize, make, _settings(keys, **extra)).run(8)
    plain = Job(optimize, make, _settings(keys, frozen="off", **extra)).run(8)
    assert frozen.loop.group is not None and plain.loop.group is None
    _same(frozen.steps, plain.steps)
    moved = [k for k in keys if np.abs(frozen.steps[-1].values[k] - frozen.steps[0].values[k]).max()
             > 0.05]
    assert moved == keys  # it stepped (the same steps as unfrozen)
    # One structure: recorded at the start (Dr.Jit records twice: a dry run, then for good;
    # after other tests in the process, once more at times), never again for the iterations'
    # new seeds: 8 iterations would make 8 recordings.
    per_group = 2 if extra.get("sensor_mode") == "step_per_sensor" else 1
    assert frozen.loop.group.recordings <= 3 * per_group
    assert frozen.loop.said == []


def test_eta_by_differences_runs_frozen_on_the_unfrozen_trajectory(optimize):
    """A dielectric's eta near the specular limit is stepped by differences of renders at
    eta +- h: those renders replay too, and the iteration's own renders come out of its
    recording, so such a job (Tables 2 and 4 of the thesis) is frozen."""
    frozen = Job(optimize, _glass, _settings([ETA])).run(8)
    plain = Job(optimize, _glass, _settings([ETA], frozen="off")).run(8)
    assert frozen.loop.group is not None and plain.loop.group is None
    eta = next(c for c in frozen.loop.active if c.name == "eta_differences")
    assert eta.on and "replayed" in _why(frozen.loop)
    _same(frozen.steps, plain.steps)
    # it stepped, towards the truth (1.5) from 1.59
    assert frozen.steps[-1].values[ETA][0] < frozen.steps[0].values[ETA][0] - 1e-3
    # the sides rendered by their recording, replayed; the loss's recording
    assert 1 <= frozen.loop.group.images.n_recordings <= 3
    assert frozen.loop.group.recordings <= 6


@pytest.mark.parametrize("value, alpha, sides_spp", [
    ("on", 0.01, {1}), ("quarter", 0.01, {1}), ("full", 0.01, {4}),
    ("on", 0.03, set()), ("quarter:0.05", 0.03, {1}), ("full:0.05", 0.03, {4})])
def test_eta_differences_render_their_sides_at_the_spp_and_below_the_width_asked(
        optimize, value, alpha, sides_spp):
    """eta_differences=full renders eta +- h at the job's spp (4), the default at a quarter;
    on glass of alpha 0.03 only a value's :ALPHA above it (0.05) turns them on."""
    from matoptd.engine.choices.eta_differences import DRAW
    job = Job(optimize, lambda: _glass(alpha), _settings([ETA], eta_differences=value))
    drawn, render = [], job.loop.renders.sensor_images

    def spy(i, n, sensor, draw, spp):
        drawn.append((draw, spp))
        return render(i, n, sensor, draw, spp)
    job.loop.renders.sensor_images = spy
    job.run(8)
    del job.loop.renders.sensor_images  # the spy's cycle would keep the scene past the test
    assert {spp for draw, spp in drawn if draw == DRAW} == sides_spp
    if sides_spp:  # toward 1.5 (at 16 px and 4 spp prb's own gradient of eta is a coin toss)
        assert job.steps[-1].values[ETA][0] < job.steps[0].values[ETA][0] - 1e-3


def test_multires_level_changes_keep_the_recording(optimize):
    job = Job(optimize, _quad, _settings([TEXTURE])).run(8)
    level = next(c for c in job.loop.choices if c.name == "multires").level[TEXTURE]
    assert level == 2  # it went through 4x4 and 8x8 to 16x16 ...
    assert job.loop.group.recordings <= 2  # ... while the scene's texture stayed 16x16


def test_a_spp_schedule_records_again_and_says_so(optimize):
    settings = {"keys": [RED, GREEN], "spp_from": {3: 8, 6: 12}}
    frozen = Job(optimize, _cornell, _settings(**settings)).run(8)
    plain = Job(optimize, _cornell, _settings(**settings, frozen="off")).run(8)
    _same(frozen.steps, plain.steps)
    assert [s.spp for s in frozen.steps] == [4, 4, 4, 8, 8, 8, 12, 12]
    assert frozen.loop.said == ["frozen: iteration 3 recorded again (spp 4 -> 8)",
                                "frozen: iteration 6 recorded again (spp 8 -> 12)"]
    assert frozen.loop.group.recordings <= 6


def test_a_checkpoint_resumes_frozen_on_the_same_trajectory(optimize):
    settings = _settings([RED, GREEN])
    first = Job(optimize, _cornell, settings).run(4)
    resumed = Job(optimize, _cornell, settings, checkpoint=first.loop.checkpoint()).run(4)
    plain = Job(optimize, _cornell, _settings([RED, GREEN], frozen="off")).run(8)
    assert resumed.steps[0].iteration == 4 and resumed.loop.group is not None
    _same(first.steps + resumed.steps, plain.steps)


def test_two_jobs_stepped_in_turn_follow_their_own_trajectories(optimize):
    """A worker switching between two jobs' scenes, one iteration at a time."""
    walls = Job(optimize, _cornell, _settings([RED, GREEN]))
    texture = Job(optimize, _quad, _settings([TEXTURE]))
    for _ in range(6):
        walls.run(1)
        texture.run(1)
    _same(walls.steps, Job(optimize, _cornell, _settings([RED, GREEN], frozen="off")).run(6).steps)
    _same(texture.steps, Job(optimize, _quad, _settings([TEXTURE], frozen="off")).run(6).steps)


def test_a_choice_that_maps_the_renders_falls_back_and_says_why(optimize):
    job = Job(optimize, _cornell, _settings([RED, GREEN], iterations=3, fit_exposure=True)).run(3)
    assert job.loop.group is None
    assert _why(job.loop) == ("not frozen: exposure_gains map the renders themselves, outside "
                              "what is recorded")
    assert next(c for c in job.loop.choices if c.name == "frozen").notes() == [
        f"frozen: {_why(job.loop)}"]


def test_moving_geometry_falls_back_and_says_why(optimize):
    key = "block.vertex_positions"
    job = Job(optimize, lambda: _cornell(block=True), _settings([key], iterations=1),
              moved=False)
    assert job.loop.group is None
    assert _why(job.loop) == (f"not frozen: {key} move geometry: each step rebuilds the "
                              "scene's acceleration structure, which a frozen function must "
                              "not do")


def test_frozen_off_is_the_unfrozen_loop(optimize):
    job = Job(optimize, _cornell, _settings([RED, GREEN], iterations=2, frozen="off"))
    assert job.loop.group is None
    status = next(c for c in job.loop.status() if c.name == "frozen")
    assert not status.on


def test_a_daemon_job_runs_frozen_with_the_history_of_the_unfrozen_one(stubs):
    scene, _, ref = cornell_with_truth(stubs, 16, 16, [])

    def job(frozen: str) -> tuple[pb.Job, list[float]]:
        spec = pb.JobSpec(scene=scene.name, iterations=6, spp=4, min_error=0, seed=3,
                          references=[pb.Reference(blob=ref.exr_blob)],
                          parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3)
                                      for k in (RED, GREEN)])
        spec.choices["frozen"] = frozen
        name = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=spec)).name
        done = wait_state(stubs, name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
        assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
        history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=name)).iterations
        return done, [h.loss for h in history]

    (frozen, a), (unfrozen, b) = job("on"), job("off")
    np.testing.assert_allclose(a, b, rtol=1e-4)
    on = next(c for c in frozen.choices if c.name == "frozen")
    assert on.on and "replayed" in on.why
    assert not next(c for c in unfrozen.choices if c.name == "frozen").on
    # the standard errors' passes follow the choice: frozen, and with it off unfrozen
    assert any(n.startswith("standard errors: J's passes frozen") for n in frozen.notes)
    assert not any("J's passes" in n for n in unfrozen.notes)


def test_a_loop_dropped_is_freed_at_once_with_its_ad_graph(optimize):
    """Nothing a job's loop holds refers back to it (its context, renders and frozen
    function hold it weakly): dropped, it goes at once rather than when Python's collector
    next runs, which may be inside a later job's AD traversal (J's forward passes refused
    the edges of a loop freed there)."""
    import gc
    import weakref
    job = Job(optimize, _cornell, _settings([RED, GREEN])).run(3)
    gone = weakref.ref(job.loop)
    collecting = gc.isenabled()
    gc.disable()
    try:
        del job
        assert gone() is None
    finally:
        if collecting:
            gc.enable()


def test_a_parked_loop_keeps_its_edges_out_of_another_runs_forward_passes(optimize):
    """A standard-error estimate may load beside a job still loaded on the worker. Mitsuba
    dispatches a BSDF's call over every live instance, the loaded glass's too, and a
    forward-mode pass (J) refused the edge from its eta to the 1/eta its plugin keeps
    ("lies outside of the current dr.isolate_grad() scope"). Parked, the glass job's scene
    holds no edge, and its next steps are those it would have taken."""
    from test_gauss_newton import _job as gauss_newton_job
    alone = Job(optimize, _glass, _settings([ETA])).run(6).steps  # its loop freed at once
    resident = Job(optimize, _glass, _settings([ETA])).run(3)
    resident.loop.park()
    other = gauss_newton_job(optimize, 4, gauss_newton="on")
    for _ in range(4):
        other.step()  # J in forward mode at its iteration 0
    resident.run(3)
    _same(resident.steps, alone)
