"""What a researcher meets on real jobs: --resolution against references of another size,
.npy initial values and ground truth on the command line, errors against the truth in the
history, a prompt end after a cancel, and notes on ranges."""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
import threading
import time

import grpc
import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import Daemon, Stubs, TOKENS, token_file, wait_iteration, wait_state
from scenes import (camera, cornell_with_truth, create_scene, glass_with_medium, png,
                    textured_quad, upload)

WALLS = ["red.reflectance.value", "green.reflectance.value"]
TEXTURE = "quad.bsdf.reflectance.data"


def matopt(address: str, *args, token: str | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, MATOPT_SERVER=address)
    env.pop("MATOPT_TOKEN", None)
    if token:
        env["MATOPT_TOKEN"] = token
    return subprocess.run([sys.executable, "-m", "matopt_client.cli", *args], capture_output=True,
                          text=True, env=env, timeout=300)


def npy(path, array) -> str:
    np.save(path, np.asarray(array, dtype=np.float32))
    return str(path)


# -- --resolution ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cornell(stubs):
    """The Cornell box at 64x64 with references rendered at that size, and its wall colours."""
    return cornell_with_truth(stubs, 64, 256, WALLS)


def recover_walls(stubs, scene, ref, resolution: int = 0, **spec) -> pb.Job:
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=40, spp=8, min_error=0, film_height=resolution,
        references=[pb.Reference(blob=ref.exr_blob, filename="ref64.exr")],
        parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3) for k in WALLS],
        **spec)))
    return wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), 300)


def walls(stubs, job: pb.Job) -> dict[str, np.ndarray]:
    result = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST))
    return {v.key: np.array(v.value) for v in result.parameters}


def test_half_resolution_scales_the_filter_and_recovers_the_walls(stubs, cornell):
    scene, truth, ref = cornell
    full, half = recover_walls(stubs, scene, ref), recover_walls(stubs, scene, ref, 32)
    assert full.state == half.state == pb.JOB_STATE_SUCCEEDED
    notes = "\n".join(half.notes)
    # The box's film has Mitsuba's default gaussian (stddev 0.5 px at 64 px): 0.25 px at 32.
    assert "sensor 0: gaussian reconstruction filter stddev scaled from 0.5 to 0.25 px" in notes
    assert "sensor 0 renders 32x32 (film was 64x64) to follow film height 32" in notes
    for job in (full, half):
        got = walls(stubs, job)
        for key in WALLS:
            assert got[key] == pytest.approx(truth[key], abs=0.06), (job.name, key, got[key])
    # half the pixels give about the same recovery, not a loss floor ten times higher
    err = {j.name: max(np.abs(walls(stubs, j)[k] - truth[k]).max() for k in WALLS)
           for j in (full, half)}
    assert err[half.name] < 2 * err[full.name] + 0.02, err


def test_bound_and_clip_notes(stubs, cornell):
    """A restart from a job's result into a narrower range is clipped (said at creation); the
    red wall's red channel, whose truth lies above the new bound, ends on it (said at the end)."""
    scene, truth, ref = cornell
    first = recover_walls(stubs, scene, ref, 32)
    red = walls(stubs, first)["red.reflectance.value"][0]
    assert red > 0.35
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(
        spec=pb.JobSpec(scene=scene.name, iterations=20, spp=4, min_error=0, film_height=32,
                        references=[pb.Reference(blob=ref.exr_blob)],
                        parameters=[pb.ParameterSpec(key="red.reflectance.value", max=0.3)]),
        initial_from_job=first.name, initial_from_which=pb.WHICH_LAST))
    clip = [n for n in job.notes if "clipped" in n]
    assert len(clip) == 1, job.notes
    assert clip[0].startswith(f"red.reflectance.value: the last result of {first.name} lies "
                              "outside the job's range [0, 0.3]")
    assert f"from {red:.4g}"[:9] in clip[0] and "to 0.3)" in clip[0]
    done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), 300)
    bound = [n for n in done.notes if "ended on its upper bound 0.3" in n]
    assert bound and bound[0].startswith("red.reflectance.value: 1 of 3 component(s)"), done.notes
    assert "widen its range" in bound[0] and "fix the parameter" in bound[0]


# -- .npy values on the command line, errors against the truth -----------------------------------

@pytest.fixture(scope="module")
def texture_scene(stubs):
    texels = np.random.default_rng(3).uniform(0.2, 0.8, (4, 4, 3))
    scene = create_scene(stubs, {"quad.xml": textured_quad().encode(),
                                 "textures/albedo.png": png(texels)}, "quad.xml")
    params = {p.key: p for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name)).parameters}
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=64)).images[0]
    truth = np.array(params[TEXTURE].value).reshape(params[TEXTURE].shape)
    return scene, ref, truth


def test_npy_init_and_truth_from_the_cli_and_history_shows_rmse_psnr(daemon, stubs,
                                                                     texture_scene, tmp_path):
    scene, ref, truth = texture_scene
    assert truth.shape == (4, 4, 3)
    init = npy(tmp_path / "init.npy", np.full(truth.shape, 0.5))
    true = npy(tmp_path / "truth.npy", truth)
    out = matopt(daemon.address, "job", "start", scene.name, "--ref", ref.exr_blob,
                 "--param", TEXTURE, "--init", f"{TEXTURE}=@{init}", "--truth",
                 f"{TEXTURE}={true}", "--iterations", "30", "--spp", "4", "--lr", "0.05",
                 "--smooth", f"{TEXTURE}=0.01", "--min-error", "0", "--wait")
    assert out.returncode == 0, out.stderr
    name = out.stdout.strip().splitlines()[0]
    job = stubs.jobs.GetJob(pb.GetJobRequest(name=name))
    assert job.spec.parameters[0].initial_blob.startswith("blobs/")
    assert job.spec.ground_truth[0].blob.startswith("blobs/")
    assert job.spec.parameters[0].smoothness == pytest.approx(0.01)

    history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=name)).iterations
    first, last = history[0].errors[0], history[-1].errors[0]
    rmse0 = np.sqrt(np.mean((0.5 - truth) ** 2))
    assert first.rmse == pytest.approx(rmse0, rel=1e-4)  # it started from init.npy
    assert first.psnr == pytest.approx(20 * np.log10(truth.max() / rmse0), abs=0.01)
    assert last.rmse < 0.6 * first.rmse and last.psnr > first.psnr
    assert len(last.correlation) == 3 and min(last.correlation) > 0.5

    shown = matopt(daemon.address, "job", "history", name)
    assert shown.returncode == 0, shown.stderr
    lines = shown.stdout.splitlines()
    assert f"ERROR {TEXTURE}" in lines[0]
    assert f"rmse {rmse0:.6g}"[:10] in lines[1] and "psnr" in lines[1] and " dB" in lines[1]
    assert ", r " in lines[-1] and "max" not in shown.stdout.lower()


def test_smooth_without_a_key_is_refused_on_the_command_line(daemon, texture_scene):
    scene, ref, truth = texture_scene
    out = matopt(daemon.address, "job", "start", scene.name, "--ref", ref.exr_blob,
                 "--param", TEXTURE, "--smooth", "0.1")
    assert out.returncode == 2, out.stderr
    assert "'0.1' names no parameter: give KEY=WEIGHT" in out.stderr, out.stderr


def test_npy_of_the_wrong_shape_is_refused_naming_file_and_shapes(daemon, stubs,
                                                                  texture_scene, tmp_path):
    scene, ref, truth = texture_scene
    wrong = npy(tmp_path / "wrong.npy", np.zeros((5, 5, 3)))
    for option in ("--init", "--truth"):
        out = matopt(daemon.address, "job", "start", scene.name, "--ref", ref.exr_blob,
                     "--param", TEXTURE, option, f"{TEXTURE}=@{wrong}")
        assert out.returncode == 2, out.stderr
        assert f"'{wrong}' has shape [5, 5, 3], but the parameter has shape [4, 4, 3]" \
            in out.stderr, out.stderr
        assert option in out.stderr
    # Through the API, a blob of the wrong size is INVALID_ARGUMENT naming the blob.
    buf = io.BytesIO()
    np.save(buf, np.zeros((5, 5, 3), np.float32))
    blob = f"blobs/{upload(stubs, buf.getvalue())}"
    with pytest.raises(grpc.RpcError) as err:
        stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
            scene=scene.name, references=[pb.Reference(blob=ref.exr_blob)],
            parameters=[pb.ParameterSpec(key=TEXTURE)],
            ground_truth=[pb.ParameterValue(key=TEXTURE, blob=blob)])))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert f"ground truth of '{TEXTURE}' ({blob}) has 75 component(s), expected 48 " \
           "(shape [4, 4, 3])" in err.value.details()


# -- cancelling a job with many sensors ----------------------------------------------------------

def ring_of_cameras(n: int, res: int) -> str:
    origins = ["0, 0, 4", "4, 0, 0", "0, 0, -4", "-4, 0, 0", "0, 4, 0.1", "0, -4, 0.1"][:n]
    return f"""<scene version="3.0.0">
    {"".join(camera(res, o) for o in origins)}
    <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
    <shape type="sphere" id="ball"><bsdf type="diffuse">
        <rgb name="reflectance" value="0.3, 0.5, 0.7"/></bsdf></shape>
</scene>"""


@pytest.fixture(scope="module")
def two_users(tmp_path_factory):
    """A daemon with alice and bob, and short slices, so that turns are frequent."""
    root = tmp_path_factory.mktemp("two_users")
    tokens = token_file(root)
    d = Daemon(root / "data", tokens, "--slice", "0.2").start()
    users = {u: Stubs(d.address, t) for u, t in TOKENS.items()}
    yield d, users
    for s in users.values():
        s.close()
    d.stop()


def test_a_glass_job_loaded_beside_a_job_estimating_its_standard_errors(two_users):
    """Alice's job ends while bob's glass job waits: bob's job loads beside it (one job per
    worker otherwise) and steps between the estimate's pieces, whose forward-mode passes
    then share the process with a scene that keeps AD edges (eta's to 1/eta). Alice's
    standard errors come whole, and bob's job goes on."""
    daemon, users = two_users
    alice, bob = users["alice"], users["bob"]
    # 64 px, 32 spp and two colours: the estimate's pieces must outlast a turn of bob's job
    # (its first ones compile) on a slow or loaded CI machine.
    box = alice.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "64", "resy": "64"}))
    box_ref = alice.scenes.RenderScene(pb.RenderSceneRequest(name=box.name, spp=64)).images[0]
    glass = create_scene(bob, {"glass.xml": glass_with_medium(16).encode()}, "glass.xml")
    glass_ref = bob.scenes.RenderScene(pb.RenderSceneRequest(name=glass.name, spp=16)).images[0]
    mine = alice.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=box.name, references=[pb.Reference(blob=box_ref.exr_blob)], iterations=40, spp=32,
        parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3)
                    for k in ("red.reflectance.value", "green.reflectance.value")])))
    wait_iteration(alice, mine.name, 2)
    other = bob.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=glass.name, references=[pb.Reference(blob=glass_ref.exr_blob)],
        iterations=100_000, spp=2,
        parameters=[pb.ParameterSpec(key="blob.bsdf.eta", initial_value=[1.4])])))
    stepped: list[float] = []  # when bob's iterations arrived

    def follow() -> None:
        with contextlib.suppress(grpc.RpcError):  # the stream ends with the test
            for event in bob.jobs.WatchJob(pb.WatchJobRequest(name=other.name)):
                if not event.HasField("job"):
                    stepped.append(time.monotonic())

    threading.Thread(target=follow, daemon=True).start()
    try:
        _estimate_beside(alice, bob, mine, other, stepped)
    finally:  # bob's endless job must not outlive the test on the module's daemon
        bob.jobs.CancelJob(pb.CancelJobRequest(name=other.name))
    wait_state(bob, other.name, (pb.JOB_STATE_CANCELLED,), 300)


def _estimate_beside(alice, bob, mine, other, stepped: list[float]) -> None:
    """Alice's job to its end with its standard errors, bob's job stepping between the
    estimate's pieces and going on after it."""
    last_iteration = 0.0  # when alice's last iteration arrived: her estimate starts after it
    noted = False
    # Arrival times, not the note's: the note can arrive after bob's first turn beside it.
    for event in alice.jobs.WatchJob(pb.WatchJobRequest(name=mine.name)):
        if not event.HasField("job"):
            last_iteration = time.monotonic()
            continue
        noted |= any(n.endswith("estimating standard errors") for n in event.job.notes)
        if event.job.state == pb.JOB_STATE_SUCCEEDED:
            break
    ended = time.monotonic()
    done = alice.jobs.GetJob(pb.GetJobRequest(name=mine.name))
    assert not any("not estimated" in n for n in done.notes), done.notes
    colours = alice.jobs.GetJobResult(pb.GetJobResultRequest(
        name=mine.name, which=pb.WHICH_LAST)).parameters
    assert sorted(c.key for c in colours) == ["green.reflectance.value", "red.reflectance.value"]
    for colour in colours:
        assert len(colour.standard_error) == 3 and np.all(np.isfinite(colour.standard_error)), \
            colour
    assert noted, done.notes
    assert any(last_iteration < t < ended for t in stepped), (last_iteration, ended, stepped)
    at = bob.jobs.GetJob(pb.GetJobRequest(name=other.name)).iteration
    wait_iteration(bob, other.name, at + 3)  # and it goes on


def test_a_paused_jobs_estimate_on_request_takes_turns_with_another_users_job(two_users):
    """Alice asks for her paused job's standard errors (a second at the least): the estimate
    runs in pieces on one worker, and bob's job, on the same worker, steps between them
    rather than waiting for the whole; alice's standard errors come whole."""
    daemon, users = two_users
    alice, bob = users["alice"], users["bob"]
    box = alice.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "24", "resy": "24"}))
    box_ref = alice.scenes.RenderScene(pb.RenderSceneRequest(name=box.name, spp=64)).images[0]
    mine = alice.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=box.name, references=[pb.Reference(blob=box_ref.exr_blob)], iterations=100_000,
        spp=4, parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3)
                           for k in ("red.reflectance.value", "green.reflectance.value")])))
    wait_iteration(alice, mine.name, 20)
    alice.jobs.PauseJob(pb.PauseJobRequest(name=mine.name))
    wait_state(alice, mine.name, (pb.JOB_STATE_PAUSED,))
    other = long_job(bob, 1)
    wait_iteration(bob, other, 3)
    stepped: list[float] = []

    def follow() -> None:
        with contextlib.suppress(grpc.RpcError):  # the stream ends with the test
            for event in bob.jobs.WatchJob(pb.WatchJobRequest(name=other)):
                if not event.HasField("job"):
                    stepped.append(time.monotonic())

    threading.Thread(target=follow, daemon=True).start()
    time.sleep(0.5)
    asked = time.monotonic()
    result = alice.jobs.GetJobResult(pb.GetJobResultRequest(
        name=mine.name, which=pb.WHICH_LAST, estimate_standard_errors=True))
    answered = time.monotonic()
    for p in result.parameters:
        assert len(p.standard_error) == 3 and pb.INTERVAL_NOT_DETERMINED not in p.interval, \
            result.standard_error_notes
    # Whole, bob's step in flight when alice asked would end its first half-second and he
    # would wait for the rest; in pieces he steps in the second half too.
    assert answered - asked > 1.0, answered - asked
    middle = asked + (answered - asked) / 2
    assert any(middle < t < answered for t in stepped), (asked, answered, stepped)
    bob.jobs.CancelJob(pb.CancelJobRequest(name=other))
    alice.jobs.CancelJob(pb.CancelJobRequest(name=mine.name))
    wait_state(bob, other, (pb.JOB_STATE_CANCELLED,), 300)


def long_job(stubs, sensors: int, resolution: int = 0) -> str:
    files = {"ring.xml": ring_of_cameras(sensors, 32).encode()}
    scene = create_scene(stubs, files, "ring.xml")
    refs = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=16)).images
    return stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=100000, spp=2, film_height=resolution,
        references=[pb.Reference(blob=r.exr_blob, filename=f"ring{r.sensor}.exr")
                    for r in refs],
        parameters=[pb.ParameterSpec(key="ball.bsdf.reflectance.value",
                                     initial_value=[0.5] * 3)]))).name


def test_a_cancelled_many_sensor_job_ends_promptly_while_others_go_on(two_users):
    daemon, users = two_users
    alice, bob = users["alice"], users["bob"]
    mine = long_job(alice, 6, resolution=24)
    other = long_job(bob, 1)
    wait_iteration(alice, mine, 3)
    wait_iteration(bob, other, 3)
    notes = alice.jobs.GetJob(pb.GetJobRequest(name=mine)).notes
    for sensor in range(6):  # every sensor's resize is said, not only the first one's
        assert any(n.startswith(f"sensor {sensor} renders 24x24 (film was 32x32)")
                   for n in notes), notes

    seen: list[tuple[float, str, pb.Job]] = []  # (when, which job, the job)

    def follow(stubs, name: str, label: str) -> None:
        try:
            watch(stubs, name, label)
        except grpc.RpcError:  # the stream of bob's job ends with the test
            pass

    def watch(stubs, name: str, label: str) -> None:
        for event in stubs.jobs.WatchJob(pb.WatchJobRequest(name=name)):
            if event.HasField("job"):
                seen.append((time.monotonic(), label, event.job))
            else:
                seen.append((time.monotonic(), label, None))
            if label == "mine" and event.HasField("job") and event.job.state == pb.JOB_STATE_CANCELLED:
                return

    watcher = threading.Thread(target=follow, args=(alice, mine, "mine"), daemon=True)
    others = threading.Thread(target=follow, args=(bob, other, "other"), daemon=True)
    others.start()
    watcher.start()
    time.sleep(0.5)
    out = matopt(daemon.address, "job", "cancel", mine, token=TOKENS["alice"])
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"{mine} RUNNING, then CANCELLED at its next iteration "
                                 "boundary (cancel requested: the job stops at its next "
                                 "iteration boundary, then renders its result images")
    assert f"'matopt job watch {mine}'" in out.stdout
    watcher.join(300)
    done = alice.jobs.GetJob(pb.GetJobRequest(name=mine))
    assert done.state == pb.JOB_STATE_CANCELLED and done.stop_reason == "cancelled"

    phases = [next((n for n in j.notes if n.startswith("end phase: ")), "")
              for _, label, j in seen if label == "mine" and j is not None]
    rendering = list(dict.fromkeys(p for p in phases if "rendering result images" in p))
    assert [p.rsplit(" ", 1)[1] for p in rendering] == [f"{k}/6" for k in range(6)], phases
    assert any(p.endswith("result images rendered (6); estimating standard errors")
               for p in phases), phases
    assert not any(n.startswith("end phase: ") for n in done.notes)
    assert any(n.startswith(f"cancelled at iteration {done.iteration}") for n in done.notes)
    # bob's job went on iterating while alice's job estimated its standard errors (at least
    # a second: engine/jacobian.py's FLOOR_SECONDS, in pieces of a step's time) on the same
    # worker, loaded beside it rather than evicting it
    estimating = next(t for t, label, j in seen if label == "mine" and j is not None
                      and any(n.endswith("estimating standard errors") for n in j.notes))
    ended = next(t for t, label, j in seen if label == "mine" and j is not None
                 and j.state == pb.JOB_STATE_CANCELLED)
    turns = [t for t, label, j in seen if label == "other" and j is None]
    assert any(estimating < t < ended for t in turns), (turns, estimating, ended)
    result = alice.jobs.GetJobResult(pb.GetJobResultRequest(name=mine, which=pb.WHICH_BEST))
    assert sorted({i.sensor for i in result.images}) == list(range(6))
    assert len(result.images) == 6 * 4
    [ball] = result.parameters
    assert len(ball.standard_error) == 3 and np.all(np.isfinite(ball.standard_error)), ball
    assert not any("not estimated" in n for n in done.notes), done.notes
    users["bob"].jobs.CancelJob(pb.CancelJobRequest(name=other))
    wait_state(bob, other, (pb.JOB_STATE_CANCELLED,), 300)
