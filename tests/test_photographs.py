"""Photographs as references: masks (a separate image, or the reference's alpha), an unknown
exposure and white balance per reference (fit_exposure), and 16-bit PNG.

Each "photograph" is the Cornell box rendered from its true values and then spoiled on purpose:
garbage in the pixels a mask leaves out, or a gain and tint of the whole image. The jobs
optimize the red and green walls from grey; the white surfaces and the light stay at their
true values, which pins the overall scale, so that a gain is identifiable (a gain and a
reflectance scale trade off otherwise).
"""

from __future__ import annotations

import json
import subprocess
import sys

import grpc
import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import Daemon, Stubs, wait_iteration, wait_state
from scenes import exr, png, upload

RES = 32
TRUTH = {"red.reflectance.value": [0.570068, 0.0430135, 0.0443706],
         "green.reflectance.value": [0.105421, 0.37798, 0.076425]}
WALLS = list(TRUTH)
TOLERANCE = 0.05  # per component, on reflectances in [0, 1]


def srgb(linear: np.ndarray) -> np.ndarray:
    """The sRGB curve (linear -> encoded), as cameras write PNG and JPEG."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def download(stubs, blob: str) -> bytes:
    return b"".join(r.chunk for r in stubs.blobs.DownloadBlob(pb.DownloadBlobRequest(name=blob)))


def decode_exr(data: bytes, tmp_path) -> np.ndarray:
    import mitsuba as mi  # the test reads the daemon's EXR files; clients never need mitsuba
    path = tmp_path / "decode.exr"
    path.write_bytes(data)
    return np.array(mi.Bitmap(str(path)), dtype=np.float32)[..., :3]


@pytest.fixture(scope="module")
def cornell(stubs, tmp_path_factory):
    """(scene, true linear render): 32x32 at 256 spp."""
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(
        overrides={"resx": str(RES), "resy": str(RES)}))
    image = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=256)).images[0]
    return scene, decode_exr(download(stubs, image.exr_blob), tmp_path_factory.mktemp("truth"))


def blob(stubs, data: bytes) -> str:
    return f"blobs/{upload(stubs, data)}"


def spec(scene: pb.Scene, references: list[pb.Reference], **options) -> pb.JobSpec:
    options = {"iterations": 60, "spp": 4, "min_error": 0, "seed": 3, **options}
    return pb.JobSpec(scene=scene.name, references=references,
                      parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3)
                                  for k in WALLS], **options)


def run(stubs, job_spec: pb.JobSpec) -> tuple[pb.Job, pb.JobResult]:
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=job_spec))
    done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), timeout=600)
    assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
    return done, stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST))


def wall_error(result: pb.JobResult) -> float:
    """The largest component error of the walls' reflectances."""
    got = {p.key: np.array(p.value) for p in result.parameters}
    return max(float(np.max(np.abs(got[k] - TRUTH[k]))) for k in WALLS)


def garbage_mask(shape: tuple[int, int]) -> np.ndarray:
    """1 where a pixel counts: a 'fixture' (a block over the back wall and the floor) and
    scattered pixels are 0; together about 40% of the image."""
    rng = np.random.default_rng(7)
    mask = (rng.uniform(size=shape) > 0.3).astype(np.float64)
    mask[RES // 3:, RES // 3: 2 * RES // 3] = 0.0
    return mask


def spoil(truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Bright noise where the mask is 0."""
    noise = np.random.default_rng(11).uniform(0.5, 3.0, truth.shape)
    return np.where(mask[..., None] > 0, truth, noise).astype(np.float32)


# -- masks -------------------------------------------------------------------------------------

def test_mask_image_keeps_garbage_out_and_unmasked_job_is_misled(stubs, cornell, tmp_path,
                                                                 cli_env):
    """Through the CLI (the client uploads the mask): the masked job finds the walls within
    tolerance; the same photograph without the mask leads the walls astray."""
    scene, truth = cornell
    mask = garbage_mask(truth.shape[:2])
    (tmp_path / "photo.exr").write_bytes(exr(spoil(truth, mask)))
    (tmp_path / "photo_mask.png").write_bytes(png(mask))
    cmd = [sys.executable, "-m", "matopt_client.cli", "job", "start", scene.name,
           "--ref", str(tmp_path / "photo.exr"), "--mask", str(tmp_path / "photo_mask.png"),
           "--iterations", "60", "--spp", "4", "--min-error", "0", "--seed", "3",
           "--wait", "--json"]
    for key in WALLS:
        cmd += ["--param", key, "--init", f"{key}=0.5,0.5,0.5"]
    out = subprocess.run(cmd, env=cli_env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    job = json.loads(out.stdout)
    assert job["spec"]["references"][0]["maskFilename"] == "photo_mask.png"
    left_out = int((mask == 0).sum())
    assert any(f"mask 'photo_mask.png' leaves out {left_out} of {RES * RES}" in n
               for n in job["notes"]), job["notes"]
    masked = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job["name"], which=pb.WHICH_LAST))
    assert wall_error(masked) < TOLERANCE, masked.parameters

    # The error image counts only what the loss counted.
    error = next(i for i in masked.images if i.role == "error")
    assert not decode_exr(download(stubs, error.exr_blob), tmp_path)[mask == 0].any()

    photo = blob(stubs, (tmp_path / "photo.exr").read_bytes())
    _, unmasked = run(stubs, spec(scene, [pb.Reference(blob=photo, filename="photo.exr")]))
    assert wall_error(unmasked) > 2 * max(wall_error(masked), TOLERANCE / 2), unmasked.parameters


def test_alpha_channel_as_mask_with_8bit_png(stubs, cornell):
    """An 8-bit RGBA PNG (sRGB): alpha 0 over the garbage and over the blown-out light."""
    scene, truth = cornell
    mask = garbage_mask(truth.shape[:2])
    mask[truth.max(axis=2) >= 1.0] = 0.0  # clipped in 8 bits: not the scene's value
    rgba = np.concatenate([srgb(spoil(truth, mask)), mask[..., None]], axis=2)
    photo = blob(stubs, png(rgba))
    done, result = run(stubs, spec(scene, [pb.Reference(blob=photo, filename="cutout.png",
                                                        alpha_mask=True)]))
    assert any("cutout.png': its alpha channel leaves out" in n for n in done.notes), done.notes
    assert wall_error(result) < TOLERANCE, result.parameters


# -- exposure and white balance ---------------------------------------------------------------

def test_fit_exposure_recovers_gain_tint_and_walls(stubs, cornell, cli_env):
    """A photograph at half the exposure with a warm white balance: with fit_exposure the
    walls come back and the gains are the factors applied. At 16 spp: plain MSE's noise term
    grows with the gain squared, which at 4 spp biases the gains several percent low."""
    scene, truth = cornell
    factors = 0.5 * np.array([1.2, 1.0, 0.8])
    photo = blob(stubs, exr(truth * factors))
    done, result = run(stubs, spec(scene, [pb.Reference(blob=photo, filename="dim.exr")],
                                   fit_exposure=True, spp=16))
    assert any("trades off against the overall scale" in n for n in done.notes), done.notes
    assert wall_error(result) < TOLERANCE, result.parameters
    [gain] = result.gains
    assert (gain.sensor, gain.reference) == (0, "dim.exr")
    assert np.array(gain.rgb) == pytest.approx(factors, rel=0.05)
    history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=done.name)).iterations
    # The first gains are the ratio of the means of photograph and initial render: already
    # about the exposure (walls at grey 0.5 instead of their colours make them off by ~20%).
    assert np.array(history[0].gains[0].rgb) == pytest.approx(factors, rel=0.3)
    assert list(history[result.iteration].gains[0].rgb) == list(gain.rgb)
    shown = subprocess.run([sys.executable, "-m", "matopt_client.cli", "job", "result", done.name,
                            "--which", "last"], env=cli_env, capture_output=True, text=True,
                           timeout=120)
    assert shown.returncode == 0, shown.stderr
    line = next(x for x in shown.stdout.splitlines() if x.startswith("gain of dim.exr:"))
    shown_rgb = [float(v.split("+-")[0]) for v in line.split(":")[1].split(",")]
    assert shown_rgb == pytest.approx(gain.rgb, rel=1e-3)  # each "value +- standard error"


def test_paused_job_goes_on_with_the_gains_it_would_have_had(stubs, cornell, tmp_path):
    """The gains and their Adam state travel in the checkpoint: a job paused and resumed (on
    single-thread workers, whose sums are deterministic) has the losses and gains of one that
    was not. Up to float32 rounding (~2e-6 seen): a gain restarted from its start or without
    its Adam moments would be off by percents."""
    _, truth = cornell
    daemon = Daemon(tmp_path / "data", None, "--workers", "2").start()
    try:
        own = Stubs(daemon.address)
        scene = own.scenes.CreateScene(pb.CreateSceneRequest(
            overrides={"resx": str(RES), "resy": str(RES)}))
        photo = blob(own, exr(truth * 0.5))
        job_spec = spec(scene, [pb.Reference(blob=photo, filename="dim.exr")],
                        fit_exposure=True, iterations=30)
        plain = own.jobs.CreateJob(pb.CreateJobRequest(spec=job_spec))
        wait_state(own, plain.name, (pb.JOB_STATE_SUCCEEDED,), timeout=300)
        paused = own.jobs.CreateJob(pb.CreateJobRequest(spec=job_spec))
        wait_iteration(own, paused.name, 8)
        own.jobs.PauseJob(pb.PauseJobRequest(name=paused.name))
        at = wait_state(own, paused.name, (pb.JOB_STATE_PAUSED,)).iteration
        assert 8 <= at < 30
        own.jobs.ResumeJob(pb.ResumeJobRequest(name=paused.name))
        done = wait_state(own, paused.name, (pb.JOB_STATE_SUCCEEDED,), timeout=300)
        # It did go through its checkpoint (else the comparison below proves nothing).
        assert done.resumed_from == f"checkpoint at iteration {at}", done.resumed_from
        runs = [own.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=j.name)).iterations
                for j in (plain, paused)]
        assert len(runs[0]) == len(runs[1]) == 30
        for field in (lambda r: [r.loss], lambda r: list(r.gains[0].rgb)):
            np.testing.assert_allclose([field(r) for r in runs[1]],
                                       [field(r) for r in runs[0]], rtol=2e-5)
        own.close()
    finally:
        daemon.stop()


# -- 16-bit PNG ---------------------------------------------------------------------------------

def test_16bit_png_is_linearised_through_srgb(stubs, cornell, tmp_path):
    """The reference the job compares against (its result's "reference" image) is the 16-bit
    PNG's values through the sRGB curve: as close to the truth as 16 bits allow, closer than
    8 bits can be."""
    scene, truth = cornell
    unclipped = truth.max(axis=2) < 1.0
    errors = {}
    for bits in (8, 16):
        photo = blob(stubs, png(srgb(truth), bits=bits))
        _, result = run(stubs, spec(scene, [pb.Reference(blob=photo, filename=f"{bits}.png")],
                                    iterations=1))
        seen = next(i for i in result.images if i.role == "reference")
        decoded = decode_exr(download(stubs, seen.exr_blob), tmp_path)
        errors[bits] = float(np.max(np.abs(decoded - truth)[unclipped]))
    assert errors[16] < 2e-4, errors
    assert errors[8] > 4 * errors[16], errors


# -- bad input ----------------------------------------------------------------------------------

def refused(stubs, job_spec: pb.JobSpec) -> str:
    with pytest.raises(grpc.RpcError) as caught:
        stubs.jobs.CreateJob(pb.CreateJobRequest(spec=job_spec))
    assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT, caught.value.details()
    return caught.value.details()


def test_bad_masks_and_gains_without_references_are_invalid_argument(stubs, cornell):
    scene, truth = cornell
    photo = blob(stubs, exr(truth))

    def with_mask(data: bytes, name: str) -> pb.JobSpec:
        return spec(scene, [pb.Reference(blob=photo, filename="photo.exr",
                                         mask_blob=blob(stubs, data), mask_filename=name)])

    message = refused(stubs, with_mask(png(np.ones((RES, RES + 8))), "wide_mask.png"))
    assert "wide_mask.png" in message and f"{RES + 8}x{RES}" in message, message
    assert "photo.exr" in message and f"{RES}x{RES}" in message, message

    message = refused(stubs, with_mask(png(np.zeros((RES, RES))), "black_mask.png"))
    assert "black_mask.png" in message and "no pixel" in message, message

    message = refused(stubs, with_mask(b"not an image at all", "notes.txt"))
    assert "mask 'notes.txt'" in message and "not a PNG, JPEG or OpenEXR" in message, message

    message = refused(stubs, spec(scene, [pb.Reference(blob=photo, filename="photo.exr",
                                                       alpha_mask=True)]))
    assert "photo.exr" in message and "no alpha channel" in message, message

    message = refused(stubs, spec(scene, [], fit_exposure=True))
    assert "fit_exposure" in message and "no reference" in message, message
