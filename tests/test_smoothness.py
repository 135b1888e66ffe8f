"""Smoothness of textures and grids (ParameterSpec.smoothness, `--smooth KEY=WEIGHT`): what a
user optimizing a texture that few pixels see gets."""

from __future__ import annotations

import grpc
import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import wait_state
from scenes import create_scene, png, textured_quad
from test_materials import recover

KEY = "quad.bsdf.reflectance.data"
SIZE = 32


def _ramp() -> np.ndarray:
    y, x = np.mgrid[0:SIZE, 0:SIZE] / (SIZE - 1)
    return np.stack([0.2 + 0.6 * x, 0.2 + 0.6 * y, 0.5 + 0.3 * (x - y)], -1)


def _roughness(texture: np.ndarray) -> float:
    """Mean squared difference of neighbouring texels."""
    t = texture.reshape(SIZE, SIZE, 3)
    return float(np.mean(np.diff(t, axis=0) ** 2) + np.mean(np.diff(t, axis=1) ** 2))


def test_smoothness_damps_the_noise_of_texels_few_pixels_see(stubs):
    """A 32x32 texture seen by an 8x8 image: about 16 texels a pixel, so most texels get a
    gradient from a few samples only. From grey, at the rate 0.03, the smoothness term ends
    with a texture far closer to the (smooth) truth than the same job without it."""
    files = {"quad.xml": textured_quad(8).encode(), "textures/albedo.png": png(_ramp())}
    truth = None
    errors, roughness = {}, {}
    for weight in (0.0, 1.0):
        params, got, done = recover(stubs, files, "quad.xml", {KEY: [0.5] * SIZE * SIZE * 3},
                                    80, spp=4, smoothness={KEY: weight}, seed=3,
                                    learning_rates={KEY: 0.03})
        truth = np.array(params[KEY].value) if params[KEY].value else truth
        if truth is None:  # too large to be listed inline: the 8-bit PNG, linearised
            truth = ((_ramp() * 255).round() / 255).ravel()
            truth = np.where(truth <= 0.04045, truth / 12.92, ((truth + 0.055) / 1.055) ** 2.4)
        errors[weight] = float(np.sqrt(np.mean((got[KEY] - truth) ** 2)))
        roughness[weight] = _roughness(got[KEY])
    # Measured: RMSE 0.027 against 0.083, roughness 0.001 against 0.011 (truth's 0.0003).
    assert errors[1.0] < 0.05 and errors[1.0] < 0.5 * errors[0.0], errors
    assert roughness[1.0] < 0.2 * roughness[0.0], roughness


@pytest.mark.parametrize("key, weight, message", [
    ("quad.bsdf.reflectance.data", -1.0, "smoothness of 'quad.bsdf.reflectance.data' must be "
                                         ">= 0, got -1.0"),
    ("quad.bsdf.reflectance.data", float("nan"), "must be >= 0, got nan"),
    ("sky.radiance.value", 0.5,
     "smoothness applies to textures and grids; 'sky.radiance.value' is of kind rgb"),
])
def test_a_bad_smoothness_is_refused_naming_the_parameter(stubs, key, weight, message):
    xml = textured_quad(8).replace(
        '<emitter type="constant">', '<emitter type="constant" id="sky">')
    scene = create_scene(stubs, {"quad.xml": xml.encode(),
                                 "textures/albedo.png": png(_ramp())}, "quad.xml")
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=4)).images[0]
    with pytest.raises(grpc.RpcError) as err:
        stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
            scene=scene.name, iterations=2, references=[pb.Reference(blob=ref.exr_blob)],
            parameters=[pb.ParameterSpec(key=key, smoothness=weight)])))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert message in err.value.details()
