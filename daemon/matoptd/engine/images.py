"""Images in and out: reference images become linear float tensors of the film's size;
renders go out as linear OpenEXR (for analysis and as references) and 8-bit sRGB PNG (for
eyes)."""

from __future__ import annotations

import os
import tempfile

import mitsuba as mi
import numpy as np

from ..engine_api import InvalidInput


def read_reference(path: str, name: str) -> np.ndarray:
    """Reads PNG/JPEG (sRGB, linearized) or EXR (already linear) as an (H, W, 3) float array.

    Nothing is clamped: HDR references keep their highlights. An image without a single
    finite pixel is refused.
    """
    try:
        bitmap = mi.Bitmap(path)
    except Exception as exc:
        raise InvalidInput(f"reference image '{name}' cannot be read as PNG, JPEG or "
                              f"OpenEXR: {str(exc).strip().splitlines()[-1]}") from None
    bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32,
                            srgb_gamma=False)
    pixels = np.array(bitmap, dtype=np.float32)
    # NaN/Inf pixels are masked out of the loss; with none left, every loss would be 0.
    if not np.isfinite(pixels).all(axis=2).any():
        raise InvalidInput(f"reference image '{name}' has no usable pixel: every one of its "
                           f"{pixels.shape[1]}x{pixels.shape[0]} pixels is NaN or infinite")
    return pixels


def fit(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resamples an (H, W, 3) image to ``size`` = (width, height) when it differs."""
    if (image.shape[1], image.shape[0]) == tuple(size):
        return image
    finite = np.where(np.isfinite(image), image, 0.0).astype(np.float32)
    out = np.array(mi.Bitmap(finite, mi.Bitmap.PixelFormat.RGB).resample(
        [int(size[0]), int(size[1])]), dtype=np.float32)
    # Pixels that were NaN/Inf stay marked, at the nearest position.
    bad = ~np.isfinite(image).all(axis=2)
    if bad.any():
        ys = (np.arange(size[1]) * image.shape[0] // size[1])[:, None]
        xs = (np.arange(size[0]) * image.shape[1] // size[0])[None, :]
        out[bad[ys, xs]] = np.nan
    return out


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
