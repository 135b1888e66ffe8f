"""Coarse-to-fine textures and grids (engine/multires.py): levels, schedule, block maps and
linear taps as pure logic; the choice's values (nearest, linear, levels, off) and a given
start kept as given, through a real daemon."""

from __future__ import annotations

import io

import grpc
import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb
from matoptd.engine.multires import (apply, downsample, index_map, level_at, levels,
                                     neighbours, taps)
from matoptd.settings import coarse_to_fine

from conftest import wait_state
from scenes import create_scene, png, textured_quad, upload


def test_levels_halve_each_side_down_to_four_and_leave_small_ones_alone():
    assert levels((16, 16, 3)) == [(4, 4, 3), (8, 8, 3), (16, 16, 3)]
    assert levels((16, 16, 16, 3)) == [(4, 4, 4, 3), (8, 8, 8, 3), (16, 16, 16, 3)]
    assert levels((12, 20, 1)) == [(6, 10, 1), (12, 20, 1)]
    assert levels((4, 4, 3)) == [(4, 4, 3)]
    assert levels((27,)) == [(27,)]  # not a texture: vertex colours, scalars


def test_the_coarse_levels_share_the_first_half_of_the_iterations():
    used = [level_at(i, 100, 3) for i in range(100)]
    assert used[:25] == [0] * 25 and used[25:50] == [1] * 25 and used[50:] == [2] * 50
    assert [level_at(i, 100, 1) for i in (0, 99)] == [0, 0]


def test_blocks_map_to_their_coarse_texel_and_means_go_back():
    index = index_map((4, 4, 1), (2, 2, 1)).reshape(4, 4)
    assert index.tolist() == [[0, 0, 1, 1], [0, 0, 1, 1], [2, 2, 3, 3], [2, 2, 3, 3]]
    fine = np.arange(16.0)
    assert downsample(fine, (4, 4, 1), (2, 2, 1)).tolist() == [2.5, 4.5, 10.5, 12.5]
    # Upsampling a coarse texture and taking block means again gives it back.
    coarse = np.random.default_rng(0).uniform(size=(3, 5, 3)).astype(np.float32)
    up = coarse.ravel()[index_map((6, 10, 3), (3, 5, 3))]
    assert np.allclose(downsample(up, (6, 10, 3), (3, 5, 3)), coarse.ravel())


def test_neighbours_pair_each_texel_with_the_next_along_each_side_within_a_channel():
    a, b = neighbours((2, 3, 2))  # 2 rows, 3 columns, 2 channels
    index = np.arange(12).reshape(2, 3, 2)
    pairs = set(zip(a.tolist(), b.tolist()))
    # 3 columns x 2 channels pairs between the rows, 2 rows x 2 column gaps x 2 channels
    assert len(pairs) == len(a) == 6 + 8
    assert (index[1, 2, 1], index[0, 2, 1]) in pairs
    assert (index[0, 1, 0], index[0, 0, 0]) in pairs
    assert all(x % 2 == y % 2 for x, y in pairs)  # never one channel against another
    assert neighbours((1, 1, 3))[0].size == 0


def test_levels_can_be_limited_to_the_finest_few():
    assert levels((16, 16, 3), 2) == [(8, 8, 3), (16, 16, 3)]
    assert levels((16, 16, 3), 1) == [(16, 16, 3)]
    assert levels((16, 16, 3), 9) == levels((16, 16, 3))


def test_linear_taps_interpolate_between_texel_centres_and_nearest_ones_copy_blocks():
    fine, coarse = (8, 6, 1), (4, 3, 1)
    ramp = (np.arange(4)[:, None] * 2.0 + np.arange(3)[None, :]).astype(np.float32)
    up = apply(ramp.ravel(), taps(fine, coarse, "linear")).reshape(8, 6)
    # a linear function stays linear inside (half a coarse texel per fine one), clamped at
    # the border; every weight set sums to 1
    assert np.allclose(np.diff(up[1:-1, 0]), 1.0) and np.allclose(np.diff(up[0, 1:-1]), 0.5)
    assert up[0, 0] == pytest.approx(0.0) and up[-1, -1] == pytest.approx(ramp[-1, -1])
    assert np.allclose(sum(w for _, w in taps(fine, coarse, "linear")), 1.0)
    near = apply(ramp.ravel(), taps(fine, coarse, "nearest")).reshape(8, 6)
    assert np.array_equal(near, np.repeat(np.repeat(ramp, 2, 0), 2, 1))


@pytest.mark.parametrize("value, parsed", [("on", ("nearest", 0)), ("linear", ("linear", 0)),
                                           ("nearest:2", ("nearest", 2))])
def test_the_choice_value_names_upsampling_and_levels(value, parsed):
    assert coarse_to_fine(value) == parsed


@pytest.mark.parametrize("value", ["cubic", "linear:0", "linear:x"])
def test_a_bad_value_says_what_it_may_be(value):
    with pytest.raises(ValueError, match="give on, off, nearest or linear, optionally with"):
        coarse_to_fine(value)


@pytest.fixture(scope="module")
def texture(stubs):
    """A 16x16 texture on a quad, its reference, and a detailed start uploaded as .npy."""
    rng = np.random.default_rng(3)
    files = {"quad.xml": textured_quad(24).encode(),
             "textures/albedo.png": png(rng.uniform(size=(16, 16, 3)))}
    scene = create_scene(stubs, files, "quad.xml")
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=8)).images[0]
    start = rng.uniform(0.2, 0.8, size=(16, 16, 3)).astype(np.float32)
    buf = io.BytesIO()
    np.save(buf, start)
    return scene, ref, start, f"blobs/{upload(stubs, buf.getvalue())}"


KEY = "quad.bsdf.reflectance.data"


def _first(stubs, texture, value: str) -> tuple[np.ndarray, pb.Job]:
    """theta_0 of a one-iteration job from the detailed start, with multires=``value``."""
    scene, ref, _, blob = texture
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=1, spp=1, references=[pb.Reference(blob=ref.exr_blob)],
        parameters=[pb.ParameterSpec(key=KEY, initial_blob=blob)],
        choices={"multires": value})))
    done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
    assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
    result = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST))
    data = b"".join(c.chunk for c in stubs.blobs.DownloadBlob(
        pb.DownloadBlobRequest(name=result.initial_parameters[0].blob)))
    return np.load(io.BytesIO(data)).reshape(16, 16, 3), done


@pytest.mark.parametrize("value", ["on", "off"])
def test_a_given_start_is_kept_as_given_unless_coarse_to_fine_is_named(stubs, texture, value):
    first, done = _first(stubs, texture, value)
    assert np.allclose(first, texture[2], atol=1e-6)
    why = next(c.why for c in done.choices if c.name == "multires")
    assert ("kept as given" in why) == (value == "on"), why


def test_named_upsampling_takes_a_given_start_coarse_to_fine(stubs, texture):
    start = texture[2]
    blocks = start.reshape(4, 4, 4, 4, 3).mean(axis=(1, 3))
    nearest, done = _first(stubs, texture, "nearest")
    assert np.allclose(nearest, np.repeat(np.repeat(blocks, 4, 0), 4, 1), atol=1e-5)
    assert "4x4 -> 8x8 -> 16x16, nearest upsampling" in next(
        c.why for c in done.choices if c.name == "multires")
    linear, done = _first(stubs, texture, "linear:2")
    assert "8x8 -> 16x16, linear upsampling" in next(
        c.why for c in done.choices if c.name == "multires")
    # block means of 2x2, interpolated: smooth, not blocky, and not the start
    assert not np.allclose(linear[0::2], linear[1::2], atol=1e-4)
    assert np.abs(linear - start).max() > 0.05
    assert linear.mean() == pytest.approx(start.mean(), abs=0.01)


def test_a_bad_multires_value_is_refused_naming_it(stubs, texture):
    scene, ref, _, blob = texture
    with pytest.raises(grpc.RpcError) as err:
        stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
            scene=scene.name, references=[pb.Reference(blob=ref.exr_blob)],
            parameters=[pb.ParameterSpec(key=KEY, initial_blob=blob)],
            choices={"multires": "cubic"})))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "choice 'multires' cannot be 'cubic'" in err.value.details()
