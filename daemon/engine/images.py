"""Images in and out: reference images become linear float tensors of the film's size;
renders go out as linear OpenEXR (for analysis and as references) and 8-bit sRGB PNG (for
eyes)."""

from __future__ import annotations

import os
import tempfile

import mitsuba as mi
import numpy as np

from ..errors import InvalidArgument


def read_reference(path: str, name: str, size: tuple[int, int]) -> mi.TensorXf:
    """Reads PNG/JPEG (sRGB, linearized) or EXR (already linear) as an RGB float tensor.

    Nothing is clamped: HDR references keep their highlights. A reference of another size but
    the same aspect ratio is resampled to the film; another aspect ratio is refused.
    """
    try:
        bitmap = mi.Bitmap(path)
    except Exception as exc:
        raise InvalidArgument(f"reference image '{name}' cannot be read as PNG, JPEG or "
                              f"OpenEXR: {str(exc).strip().splitlines()[-1]}") from None
    bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32,
                            srgb_gamma=False)
    w, h = bitmap.size()
    if (w, h) != tuple(size):
        if abs(w / h - size[0] / size[1]) > 0.01:
            raise InvalidArgument(f"reference image '{name}' is {w}x{h} but its sensor renders "
                                  f"{size[0]}x{size[1]}: the aspect ratios differ")
        bitmap = bitmap.resample([int(size[0]), int(size[1])])
    return mi.TensorXf(np.array(bitmap, dtype=np.float32))


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
