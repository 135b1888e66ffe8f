"""Images in and out: reference images (with their masks) become linear float tensors of the
film's size and per-pixel weights; renders go out as linear OpenEXR (for analysis and as
references) and 8-bit sRGB PNG (for eyes)."""

from __future__ import annotations

import os
import tempfile

from typing import Callable

import mitsuba as mi
import numpy as np

from .. import engine_api as api
from ..engine_api import InvalidInput


def _open(path: str, what: str) -> mi.Bitmap:
    try:
        return mi.Bitmap(path)
    except Exception as exc:
        raise InvalidInput(f"{what} cannot be read as PNG, JPEG or OpenEXR: "
                           f"{str(exc).strip().splitlines()[-1]}") from None


def _has_alpha(bitmap: mi.Bitmap) -> bool:
    return bitmap.pixel_format() in (mi.Bitmap.PixelFormat.RGBA, mi.Bitmap.PixelFormat.YA)


def _size(a: np.ndarray) -> str:
    return f"{a.shape[1]}x{a.shape[0]}"


def read_reference(path: str, name: str, alpha: bool = False
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """Reads PNG/JPEG (sRGB, linearized, 8 or 16 bit) or EXR (already linear) as an (H, W, 3)
    float array, and with ``alpha`` its straight alpha channel as an (H, W) array.

    Nothing is clamped: HDR references keep their highlights. An image without a single
    finite pixel is refused, as is ``alpha`` for an image without an alpha channel.
    """
    bitmap = _open(path, f"reference image '{name}'")
    pixels = np.array(bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32,
                                     srgb_gamma=False), dtype=np.float32)
    # NaN/Inf pixels are masked out of the loss; with none left, every loss would be 0.
    if not np.isfinite(pixels).all(axis=2).any():
        raise InvalidInput(f"reference image '{name}' has no usable pixel: every one of its "
                           f"{_size(pixels)} pixels is NaN or infinite")
    if not alpha:
        return pixels, None
    if not _has_alpha(bitmap):
        layout = str(bitmap.pixel_format()).split(".")[-1]
        raise InvalidInput(f"reference image '{name}' has no alpha channel to use as its mask "
                           f"(alpha_mask): its pixels are {layout}")
    # Alpha carries no tone curve; converting keeps it straight (not premultiplied).
    rgba = np.array(bitmap.convert(mi.Bitmap.PixelFormat.RGBA, mi.Struct.Type.Float32,
                                   srgb_gamma=False), dtype=np.float32)
    return pixels, np.nan_to_num(np.clip(rgba[..., 3], 0.0, 1.0))


def read_mask(path: str, name: str) -> np.ndarray:
    """A mask image as (H, W) weights in [0, 1]: its first channel as stored, without the
    sRGB curve (8- and 16-bit values scale to [0, 1]; OpenEXR values are clipped)."""
    bitmap = _open(path, f"mask '{name}'")
    raw = np.array(bitmap.convert(bitmap.pixel_format(), mi.Struct.Type.Float32,
                                  srgb_gamma=bitmap.srgb_gamma()), dtype=np.float32)
    first = raw if raw.ndim == 2 else raw[..., 0]
    return np.nan_to_num(np.clip(first, 0.0, 1.0))


def load_reference(reference: api.ReferenceInput, blob: Callable[[str], str]
                   ) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """A reference image, its (H, W) weights and notes on what they leave out.

    The weight of a pixel is its mask's value times its alpha (when asked for), and 0 where the
    reference is NaN/Inf. ``blob`` maps a digest to a local file. Refused (naming the files):
    a mask of another size than the reference, and weights that leave no pixel to compare.
    """
    name = reference.name
    picture, alpha = read_reference(blob(reference.sha256), name, reference.alpha_mask)
    weight = np.isfinite(picture).all(axis=2).astype(np.float32)
    notes = []
    bad = int(weight.size - weight.sum())
    if bad:
        notes.append(f"reference '{name}': {bad} NaN/Inf pixel(s) masked out of the loss")
    if alpha is not None:
        if not alpha.any():
            raise InvalidInput(f"reference image '{name}' is transparent everywhere: its alpha "
                               f"channel (alpha_mask) is 0 at all {_size(alpha)} pixels")
        weight *= alpha
        notes.append(f"reference '{name}': its alpha channel leaves out "
                     f"{_count(alpha)} of {alpha.size} pixel(s)")
    if reference.mask_sha256:
        mask_name = reference.mask_name
        mask = read_mask(blob(reference.mask_sha256), mask_name)
        if mask.shape != weight.shape:
            raise InvalidInput(f"mask '{mask_name}' is {_size(mask)} px, but its reference "
                               f"image '{name}' is {_size(picture)} px: a mask must have the "
                               "reference's size")
        if not mask.any():
            raise InvalidInput(f"mask '{mask_name}' of reference '{name}' leaves no pixel to "
                               f"compare: it is 0 (black) at all {_size(mask)} pixels")
        weight *= mask
        notes.append(f"reference '{name}': mask '{mask_name}' leaves out {_count(mask)} of "
                     f"{mask.size} pixel(s)")
    if not weight.any():
        raise InvalidInput(f"reference image '{name}' has no pixel left to compare: its mask, "
                           "alpha channel and NaN/Inf pixels together leave out all "
                           f"{_size(weight)} of them")
    return np.where(weight[..., None] > 0, picture, 0.0).astype(np.float32), weight, notes


def _count(weight: np.ndarray) -> int:
    """Pixels a weight leaves out entirely."""
    return int(np.sum(weight <= 0))


def _resample(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return np.array(mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32),
                              mi.Bitmap.PixelFormat.RGB).resample([int(size[0]), int(size[1])]),
                    dtype=np.float32)


def fit(image: np.ndarray, weight: np.ndarray, size: tuple[int, int]
        ) -> tuple[np.ndarray, np.ndarray]:
    """Resamples an (H, W, 3) image and its (H, W) weights to ``size`` = (width, height) when
    it differs. Pixels are averaged by weight, so that left-out pixels (background, NaN) do
    not bleed into the ones that count."""
    if (image.shape[1], image.shape[0]) == tuple(size):
        return image, weight
    if weight.min() >= 1.0:
        return _resample(image, size), np.ones((size[1], size[0]), dtype=np.float32)
    w3 = np.repeat(weight[..., None], 3, axis=2)
    total = _resample(w3 * image, size)
    w = _resample(w3, size)[..., 0]
    # The resampling filter rings slightly past [0, 1]; a sliver of weight is no pixel.
    keep = w > 1e-3
    out = np.where(keep[..., None], total / np.maximum(w, 1e-3)[..., None], 0.0)
    return out.astype(np.float32), np.where(keep, np.clip(w, 0.0, 1.0), 0.0).astype(np.float32)


def _encode(bitmap: mi.Bitmap, suffix: str) -> bytes:
    fd, path = tempfile.mkstemp(suffix=suffix)
    os.close(fd)
    try:
        bitmap.write(path)
        with open(path, "rb") as f:
            return f.read()
    finally:
        os.unlink(path)


def encode(image: np.ndarray) -> tuple[bytes, bytes]:
    """(OpenEXR, PNG) bytes of a linear RGB image."""
    rgb = np.ascontiguousarray(image[..., :3], dtype=np.float32)
    exr = _encode(mi.Bitmap(rgb, mi.Bitmap.PixelFormat.RGB), ".exr")
    ldr = mi.Bitmap(np.nan_to_num(rgb, nan=0.0, posinf=1.0, neginf=0.0),
                    mi.Bitmap.PixelFormat.RGB).convert(
        mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)
    return exr, _encode(ldr, ".png")
