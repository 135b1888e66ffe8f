"""Coarse-to-fine textures and grids (engine/multires.py): levels, schedule and block maps,
as pure logic."""

from __future__ import annotations

import numpy as np

from matoptd.engine.multires import downsample, index_map, level_at, levels, neighbours


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
