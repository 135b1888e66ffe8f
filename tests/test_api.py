"""The v1 API through the generated stubs: blobs, scenes, parameters, renders, job control."""

from __future__ import annotations

import hashlib
import os
import time

import grpc
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import wait_iteration, wait_state
from scenes import MESH_SCENE, QUAD_OBJ, create_scene, upload

WALLS = ["red.reflectance.value", "green.reflectance.value", "white.reflectance.value"]


def test_large_blob_travels_in_chunks_and_is_not_sent_twice(stubs):
    data = os.urandom(5 * (1 << 20) + 123)  # above gRPC's 4 MiB message limit
    sha = hashlib.sha256(data).hexdigest()
    assert stubs.blobs.FindMissingBlobs(pb.FindMissingBlobsRequest(sha256=[sha])).missing_sha256 == [sha]
    upload(stubs, data)
    assert not stubs.blobs.FindMissingBlobs(pb.FindMissingBlobsRequest(sha256=[sha])).missing_sha256
    back = b"".join(r.chunk for r in stubs.blobs.DownloadBlob(pb.DownloadBlobRequest(name=f"blobs/{sha}")))
    assert back == data


def test_upload_with_wrong_digest_is_refused(stubs):
    def parts():
        yield pb.UploadBlobRequest(header=pb.UploadBlobRequest.Header(sha256="0" * 64, size_bytes=3))
        yield pb.UploadBlobRequest(chunk=b"abc")
    with pytest.raises(grpc.RpcError) as err:
        stubs.blobs.UploadBlob(parts())
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "hashes to" in err.value.details()


def test_bundle_with_subfolder_and_windows_separator_loads_with_stable_keys(stubs):
    files = {"scene.xml": MESH_SCENE.encode(), "meshes/quad.obj": QUAD_OBJ.encode()}
    first = create_scene(stubs, files, "scene.xml", res=24)
    again = create_scene(stubs, files, "scene.xml", res=24)
    assert [(s.width, s.height) for s in first.sensors] == [(24, 24)]
    keys = [p.key for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=first.name)).parameters]
    # The unnamed shape gets a name from its position, the same on every load.
    assert "shape_0.bsdf.reflectance.value" in keys
    assert keys == [p.key for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=again.name)).parameters]
    assert not any(k.startswith("object_") for k in keys)


def test_cornell_box_parameters_have_kinds_values_and_ranges(stubs):
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "32", "resy": "32"}))
    assert scene.display_name == "cornell-box" and scene.sensors[0].width == 32
    params = {p.key: p for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name)).parameters}
    red = params["red.reflectance.value"]
    assert red.kind == pb.PARAMETER_KIND_RGB and list(red.shape) == [3]
    assert red.value == pytest.approx([0.570068, 0.0430135, 0.0443706], abs=1e-6)
    assert (red.min, red.max, red.default_learning_rate) == (0.0, 1.0, pytest.approx(0.1))
    assert params["light.emitter.radiance.value"].max == float("inf")
    assert params["small-box.vertex_positions"].kind == pb.PARAMETER_KIND_VERTEX_ARRAY


def test_override_not_declared_is_a_warning_not_an_error(stubs):
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "32", "resy": "32",
                                                                      "bogus": "1"}))
    assert any("bogus" in w for w in scene.warnings)


def test_request_id_makes_creation_idempotent(stubs):
    req = pb.CreateSceneRequest(overrides={"resx": "32", "resy": "32"}, request_id="r-1")
    assert stubs.scenes.CreateScene(req).name == stubs.scenes.CreateScene(req).name


def test_render_with_overridden_parameter_changes_only_that(stubs):
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "32", "resy": "32"}))
    dark = stubs.scenes.RenderScene(pb.RenderSceneRequest(
        name=scene.name, spp=16,
        parameters=[pb.ParameterValue(key="white.reflectance.value", value=[0, 0, 0])]))
    image = dark.images[0]
    assert (image.width, image.height, image.role) == (32, 32, "render")
    png = b"".join(r.chunk for r in stubs.blobs.DownloadBlob(pb.DownloadBlobRequest(name=image.png_blob)))
    assert png.startswith(b"\x89PNG")
    exr = b"".join(r.chunk for r in stubs.blobs.DownloadBlob(pb.DownloadBlobRequest(name=image.exr_blob)))
    assert exr[:4] == b"\x76\x2f\x31\x01"  # OpenEXR magic
    # The scene itself keeps its value.
    params = {p.key: p for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name)).parameters}
    assert params["white.reflectance.value"].value[0] == pytest.approx(0.885809, abs=1e-6)


def _cornell_job(stubs, iterations: int, **spec) -> tuple[pb.Scene, pb.Job]:
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "32", "resy": "32"}))
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=64)).images[0]
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=iterations,
        references=[pb.Reference(blob=ref.exr_blob, filename="ref.exr")],
        parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3) for k in WALLS], **spec)))
    return scene, job


def test_watch_sends_state_first_then_iterations_then_final_state(stubs):
    _, job = _cornell_job(stubs, 5)
    events = list(stubs.jobs.WatchJob(pb.WatchJobRequest(name=job.name)))
    assert events[0].HasField("job")
    assert events[-1].job.state == pb.JOB_STATE_SUCCEEDED
    iterations = [e.iteration for e in events if e.HasField("iteration")]
    assert [r.iteration for r in iterations] == list(range(iterations[0].iteration, 5))
    assert all(r.seconds > 0 and r.loss > 0 for r in iterations)
    assert {p.key for p in iterations[-1].parameters} == set(WALLS)
    done = stubs.jobs.GetJob(pb.GetJobRequest(name=job.name))
    assert done.integrator == "prb" and "surface materials" in done.integrator_reason
    assert list(done.sensors_rendered) == [0] and done.nonfinite_gradient_steps == 0


def test_best_result_holds_the_parameters_that_produced_its_loss(stubs):
    _, job = _cornell_job(stubs, 8)
    wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED,))
    history = {r.iteration: r for r in stubs.jobs.GetJobHistory(
        pb.GetJobHistoryRequest(name=job.name)).iterations}
    assert sorted(history) == list(range(8))
    best = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_BEST))
    assert best.loss == min(r.loss for r in history.values())
    recorded = {p.key: list(p.value) for p in history[best.iteration].parameters}
    assert {p.key: list(p.value) for p in best.parameters} == recorded
    assert sorted(i.role for i in best.images) == ["error", "initial", "optimized", "reference"]
    last = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST))
    assert last.iteration == 7


def test_pause_resume_cancel(stubs):
    """A paused job does no iterations for a span in which it did several while running, and
    a resumed one goes on from where it stopped."""
    _, job = _cornell_job(stubs, 100_000)
    # Its pace as it runs here and now, so that the wait below is long enough on a busy machine.
    began = wait_iteration(stubs, job.name, 2).iteration
    t0 = time.monotonic()
    wait_iteration(stubs, job.name, began + 5)
    span = max(1.5, 2 * (time.monotonic() - t0))  # ~10 iterations' worth, were it running
    stubs.jobs.PauseJob(pb.PauseJobRequest(name=job.name))
    paused = wait_state(stubs, job.name, (pb.JOB_STATE_PAUSED,))
    at = paused.iteration
    time.sleep(span)
    still = stubs.jobs.GetJob(pb.GetJobRequest(name=job.name))
    assert (still.state, still.iteration) == (pb.JOB_STATE_PAUSED, at)  # it stays put
    history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=job.name, page_size=1000))
    assert [r.iteration for r in history.iterations][-1] == at - 1
    stubs.jobs.ResumeJob(pb.ResumeJobRequest(name=job.name))
    resumed = wait_iteration(stubs, job.name, at + 3)  # it moves again, from where it stopped
    assert resumed.resumed_from == f"checkpoint at iteration {at}"
    stubs.jobs.CancelJob(pb.CancelJobRequest(name=job.name))
    cancelled = wait_state(stubs, job.name, (pb.JOB_STATE_CANCELLED,))
    assert at + 3 <= cancelled.iteration < 100_000
    # A cancelled job keeps what it found so far.
    best = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name))
    assert len(best.parameters) == 3
    with pytest.raises(grpc.RpcError) as err:
        stubs.jobs.ResumeJob(pb.ResumeJobRequest(name=job.name))
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION


def test_two_jobs_take_turns(stubs):
    # Jobs share a worker in slices of seconds: long enough jobs take turns.
    _, a = _cornell_job(stubs, 5000)
    _, b = _cornell_job(stubs, 5000)
    wait_state(stubs, b.name, (pb.JOB_STATE_RUNNING,))
    ja = stubs.jobs.GetJob(pb.GetJobRequest(name=a.name))
    assert ja.state == pb.JOB_STATE_RUNNING and ja.iteration < 5000  # b started before a finished
    # and a gets its turn again after b's: neither is starved
    jb = wait_iteration(stubs, b.name, 1)
    wait_iteration(stubs, a.name, ja.iteration + 1)
    wait_iteration(stubs, b.name, jb.iteration + 1)
    for job in (a, b):
        stubs.jobs.CancelJob(pb.CancelJobRequest(name=job.name))
        wait_state(stubs, job.name, (pb.JOB_STATE_CANCELLED,))


def test_list_jobs_pages(stubs):
    names = [_cornell_job(stubs, 1)[1].name for _ in range(3)]
    for n in names:
        wait_state(stubs, n, (pb.JOB_STATE_SUCCEEDED,))
    seen, token = [], ""
    while True:
        page = stubs.jobs.ListJobs(pb.ListJobsRequest(page_size=2, page_token=token))
        assert len(page.jobs) <= 2
        seen += [j.name for j in page.jobs]
        token = page.next_page_token
        if not token:
            break
    assert set(names) <= set(seen)


def test_film_follows_the_reference_aspect_ratio_and_nan_pixels_are_masked(stubs, tmp_path):
    """A 2:1 reference for a square film: the sensor renders 2:1 at the film's height, or at
    the job's resolution; NaN/Inf pixels are masked out and counted, never poisoning the loss."""
    wide = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "48", "resy": "24"}))
    exr = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=wide.name, spp=16)).images[0]
    data = b"".join(r.chunk for r in stubs.blobs.DownloadBlob(
        pb.DownloadBlobRequest(name=exr.exr_blob)))
    import mitsuba as mi  # the test writes an EXR with holes; clients never need mitsuba
    mi.set_variant("scalar_rgb")
    (tmp_path / "w.exr").write_bytes(data)
    pixels = __import__("numpy").array(mi.Bitmap(str(tmp_path / "w.exr")))
    pixels[0, :5] = float("nan")
    pixels[1, :3] = float("inf")
    mi.Bitmap(pixels).write(str(tmp_path / "holes.exr"))
    sha = upload(stubs, (tmp_path / "holes.exr").read_bytes())

    square = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "32", "resy": "32"}))
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=square.name, iterations=3, film_height=20,
        references=[pb.Reference(blob=f"blobs/{sha}", filename="holes.exr")],
        parameters=[pb.ParameterSpec(key="red.reflectance.value")])))
    done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
    assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
    assert any("8 NaN/Inf pixel(s) masked" in n for n in done.notes), done.notes
    assert any("renders 40x20" in n for n in done.notes), done.notes
    history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=job.name)).iterations
    assert all(r.loss == r.loss for r in history)  # finite
    image = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name)).images[0]
    assert (image.width, image.height) == (40, 20)


def test_ground_truth_gives_parameter_errors_and_image_error(stubs):
    _, job = _cornell_job(stubs, 6, ground_truth=[
        pb.ParameterValue(key="red.reflectance.value", value=[0.570068, 0.0430135, 0.0443706])],
        image_error_every=2, image_error_spp=8)
    wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED,))
    history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=job.name)).iterations
    first = history[0].errors[0]
    assert first.key == "red.reflectance.value"
    assert first.max_abs == pytest.approx(0.5 - 0.0430135, abs=1e-5)  # started from grey
    assert [r.HasField("image_error") for r in history] == [True, False, True, False, True, True]
    assert all(r.image_error > 0 for r in history if r.HasField("image_error"))


def test_restart_from_a_finished_job_starts_where_it_ended(stubs):
    scene, job = _cornell_job(stubs, 4)
    wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED,))
    last = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST))
    ended = {v.key: list(v.value) for v in last.parameters}
    old = stubs.jobs.GetJob(pb.GetJobRequest(name=job.name)).spec
    spec = pb.JobSpec()
    spec.CopyFrom(old)
    spec.iterations, spec.spp = 2, 2          # edited settings
    for p in spec.parameters:
        del p.initial_value[:]
    spec.parameters[0].initial_value[:] = [0.1, 0.2, 0.3]  # and one edited initial value
    again = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=spec, initial_from_job=job.name,
                                                     initial_from_which=pb.WHICH_LAST))
    starts = {p.key: list(p.initial_value) for p in again.spec.parameters}
    assert starts[WALLS[0]] == pytest.approx([0.1, 0.2, 0.3])
    for key in WALLS[1:]:
        assert starts[key] == ended[key]
    done = wait_state(stubs, again.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
    assert done.state == pb.JOB_STATE_SUCCEEDED and done.spec.iterations == 2
