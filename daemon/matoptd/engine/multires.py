"""Coarse-to-fine optimization of textures and grids.

A texture (H, W, C) or grid (Z, Y, X, C) of many texels is optimized first at a coarse
resolution, each coarse texel standing for a block of the full one (nearest upsampling, by
a gather, so gradients sum over the block), then at twice that, up to the full resolution
by half the iterations. Every coarse texel is seen by many pixels, so its gradient carries
far less noise than a single texel's: the low frequencies of the pattern (and its average
tint, which scalars such as spec_trans would otherwise absorb) settle first, the detail
after. Sides are halved down to at least MIN_SIDE; smaller parameters are left as they are.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

MIN_SIDE = 4


def levels(shape: tuple[int, ...]) -> list[tuple[int, ...]]:
    """The shapes from coarsest to full, or [shape] when it is too small (or not a texture or
    grid). The last axis (channels) is kept."""
    if len(shape) not in (3, 4):
        return [tuple(shape)]
    out = [tuple(shape)]
    while min(out[-1][:-1]) >= 2 * MIN_SIDE:
        out.append(tuple(math.ceil(s / 2) for s in out[-1][:-1]) + (shape[-1],))
    return out[::-1]


def level_at(iteration: int, iterations: int, count: int) -> int:
    """Which level iteration i uses: the coarse ones share the first half evenly."""
    if count <= 1:
        return 0
    coarse = count - 1
    span = max(1, iterations // 2)
    return min(coarse, iteration * coarse // span)


def index_map(fine: tuple[int, ...], coarse: tuple[int, ...]) -> np.ndarray:
    """For each element of ``fine`` (flat, C order), the flat index of the coarse element
    whose block contains it."""
    axes = [np.arange(f) * c // f for f, c in zip(fine[:-1], coarse[:-1])]
    grids = np.meshgrid(*axes, np.arange(fine[-1]), indexing="ij")
    return np.ravel_multi_index(grids, coarse).ravel().astype(np.uint32)


def upsample(latent: mi.TensorXf, fine: tuple[int, ...], index: mi.UInt32) -> mi.TensorXf:
    """The coarse tensor blown up to ``fine`` (differentiable)."""
    return mi.TensorXf(dr.gather(mi.Float, latent.array, index), fine)


def downsample(values: np.ndarray, fine: tuple[int, ...], coarse: tuple[int, ...]) -> np.ndarray:
    """Block means of a flat ``fine`` array: a start at the coarse level."""
    index = index_map(fine, coarse)
    total = np.bincount(index, weights=np.asarray(values, np.float64).ravel(),
                        minlength=int(np.prod(coarse)))
    count = np.bincount(index, minlength=int(np.prod(coarse)))
    return (total / np.maximum(count, 1)).astype(np.float32)


def neighbours(shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (a, b) of every pair of elements adjacent along a spatial axis of
    ``shape`` (the last axis, channels, pairs a channel with itself only)."""
    index = np.arange(int(np.prod(shape))).reshape(shape)
    firsts, seconds = [], []
    for axis in range(len(shape) - 1):
        if shape[axis] < 2:
            continue
        lead = [slice(None)] * len(shape)
        lead[axis] = slice(1, None)
        trail = [slice(None)] * len(shape)
        trail[axis] = slice(None, -1)
        firsts.append(index[tuple(lead)].ravel())
        seconds.append(index[tuple(trail)].ravel())
    if not firsts:
        return np.zeros(0, np.uint32), np.zeros(0, np.uint32)
    return (np.concatenate(firsts).astype(np.uint32), np.concatenate(seconds).astype(np.uint32))
