"""Coarse-to-fine optimization of textures and grids.

A texture (H, W, C) or grid (Z, Y, X, C) of many texels is optimized first at a coarse
resolution, each coarse texel standing for a block of the full one (nearest upsampling, by
a gather, so gradients sum over the block; or linear, a weighted sum of the 2^d nearest
coarse texels, which leaves no block edges), then at twice that, up to the full resolution
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


def levels(shape: tuple[int, ...], count: int = 0) -> list[tuple[int, ...]]:
    """The shapes from coarsest to full, or [shape] when it is too small (or not a texture or
    grid): the finest ``count`` of them (0: all). The last axis (channels) is kept."""
    if len(shape) not in (3, 4):
        return [tuple(shape)]
    out = [tuple(shape)]
    while min(out[-1][:-1]) >= 2 * MIN_SIDE and (count == 0 or len(out) < count):
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


Taps = list[tuple[np.ndarray, np.ndarray | None]]  # (coarse index, weight) per fine element


def taps(fine: tuple[int, ...], coarse: tuple[int, ...], mode: str) -> Taps:
    """How each element of ``fine`` is made from ``coarse``: ``nearest``, the one element
    whose block contains it (weight None: 1); ``linear``, the 2^d nearest texel centres
    (bilinear, trilinear), their weights summing to 1, clamped at the border."""
    if mode == "nearest":
        return [(index_map(fine, coarse), None)]
    per_axis = []
    for f, c in zip(fine[:-1], coarse[:-1]):
        x = np.clip((np.arange(f) + 0.5) * c / f - 0.5, 0, c - 1)
        lo = np.floor(x).astype(np.int64)
        per_axis.append(((lo, np.minimum(lo + 1, c - 1)), (1 - (x - lo), x - lo)))
    out: Taps = []
    for corner in np.ndindex(*(2,) * len(per_axis)):
        index = [axis[0][b] for axis, b in zip(per_axis, corner)]
        weight = [axis[1][b] for axis, b in zip(per_axis, corner)]
        grids = np.meshgrid(*index, np.arange(fine[-1]), indexing="ij")
        weights = np.meshgrid(*weight, np.ones(fine[-1]), indexing="ij")
        out.append((np.ravel_multi_index(grids, coarse).ravel().astype(np.uint32),
                    np.prod(weights, axis=0).ravel().astype(np.float32)))
    return out


def apply(values: np.ndarray, made: Taps) -> np.ndarray:
    """The fine array ``made`` from the coarse ``values`` (flat, numpy)."""
    values = np.asarray(values, np.float32).ravel()
    return sum(values[i] if w is None else w * values[i] for i, w in made)


def upsample(latent: mi.TensorXf, fine: tuple[int, ...], made) -> mi.TensorXf:
    """The coarse tensor blown up to ``fine`` (differentiable); ``made``: taps() as Dr.Jit
    arrays."""
    out = 0
    for index, weight in made:
        gathered = dr.gather(mi.Float, latent.array, index)
        out = out + (gathered if weight is None else weight * gathered)
    return mi.TensorXf(out, fine)


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
