"""Image dimensions read from a file's header, in pure Python, before anything decodes it.

A 600 KB PNG can decode to 25000x25000 pixels (7.9 GB as float RGB); a decoder learns that
only once it has allocated the memory. Here the width, height and channel layout come from the
header alone (PNG: IHDR; JPEG: the SOF segment; OpenEXR: the ``dataWindow`` and ``channels``
attributes), so that admission can refuse the image first. Only what the header says is
trusted as far as it is needed for an estimate; the decoder in the worker still reads the
whole file, and refuses what is broken beyond the header.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import BinaryIO

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_START = b"\xff\xd8"
EXR_MAGIC = b"\x76\x2f\x31\x01"

# PNG colour types: channels after decoding (a palette expands to RGB).
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}
# JPEG start-of-frame markers (baseline, progressive, lossless, arithmetic, hierarchical);
# C4 (Huffman tables), C8 (reserved) and CC (arithmetic conditioning) share the range.
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_STANDALONE = {0x01, *range(0xD0, 0xD8)}  # TEM and RST0-7 carry no length
_JPEG_SOS, _JPEG_EOI = 0xDA, 0xD9
# OpenEXR pixel types: UINT, HALF, FLOAT.
_EXR_SAMPLE_BYTES = {0: 4, 1: 2, 2: 4}
_EXR_MULTIPART = 0x1000
_EXR_MAX_NAME = 255  # bytes of an attribute name or type (with the long-names flag)
# Segments or attributes read before giving up: real files have a few dozen; a crafted one
# must not keep the daemon reading millions of tiny records.
_MAX_RECORDS = 4096


class BadHeader(ValueError):
    """The header is not one of a PNG, JPEG or OpenEXR file, or is broken; the message names
    the file."""


@dataclass(frozen=True)
class ImageHeader:
    format: str          # "PNG", "JPEG" or "OpenEXR"
    width: int
    height: int
    channels: int
    sample_bytes: int    # bytes of all channels of one pixel, as the decoder holds them

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def decoded_bytes(self) -> int:
        """Memory a decode takes: the file's own pixel layout, then its float RGB copy."""
        return self.pixels * (self.sample_bytes + 3 * 4)


def read_header(f: BinaryIO, name: str, what: str = "reference image") -> ImageHeader:
    """The dimensions of the image in ``f`` (a binary file positioned at its start);
    ``name`` is the user's file name and ``what`` the image's role, for messages."""
    start = f.read(8)
    try:
        if start.startswith(PNG_SIGNATURE):
            header = _png(f)
        elif start.startswith(JPEG_START):
            f.seek(2)
            header = _jpeg(f)
        elif start.startswith(EXR_MAGIC):
            header = _exr(f, struct.unpack("<I", start[4:8])[0] if len(start) == 8 else 0)
        else:
            raise BadHeader("not a PNG, JPEG or OpenEXR file")
    except (BadHeader, struct.error) as exc:
        why = str(exc) if isinstance(exc, BadHeader) else "its header is truncated"
        raise BadHeader(f"{what} '{name}' cannot be read: {why}") from None
    if header.width < 1 or header.height < 1:
        raise BadHeader(f"{what} '{name}' cannot be read: its {header.format} header "
                        f"gives a size of {header.width}x{header.height} pixels")
    return header


def _exactly(f: BinaryIO, n: int) -> bytes:
    data = f.read(n)
    if len(data) != n:
        raise BadHeader("its header is truncated")
    return data


def _png(f: BinaryIO) -> ImageHeader:
    """IHDR must be the first chunk: width, height, bit depth, colour type."""
    length, kind = struct.unpack(">I4s", _exactly(f, 8))
    if kind != b"IHDR" or length != 13:
        raise BadHeader("its PNG header has no IHDR chunk first")
    width, height, depth, colour = struct.unpack(">IIBB", _exactly(f, 10))
    if colour not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16):
        raise BadHeader(f"its PNG header gives colour type {colour} at bit depth {depth}")
    channels = _PNG_CHANNELS[colour]
    return ImageHeader("PNG", width, height, channels, channels * (2 if depth == 16 else 1))


def _jpeg(f: BinaryIO) -> ImageHeader:
    """Segments up to the first start-of-frame: precision, height, width, components."""
    for _ in range(_MAX_RECORDS):
        if _exactly(f, 1) != b"\xff":
            raise BadHeader("its JPEG segments are broken (a marker was expected)")
        marker = _exactly(f, 1)[0]
        if marker == 0xFF:  # a fill byte; the marker follows
            f.seek(-1, 1)
            continue
        if marker in _JPEG_STANDALONE:
            continue
        if marker in (_JPEG_SOS, _JPEG_EOI):
            raise BadHeader("its JPEG data has no frame header (SOF) before the image data")
        (length,) = struct.unpack(">H", _exactly(f, 2))
        if length < 2:
            raise BadHeader(f"its JPEG segment 0xFF{marker:02X} has length {length}")
        if marker in _JPEG_SOF:
            precision, height, width, components = struct.unpack(">BHHB", _exactly(f, 6))
            if components < 1:
                raise BadHeader("its JPEG frame header gives 0 components")
            return ImageHeader("JPEG", width, height, components,
                               components * (2 if precision > 8 else 1))
        f.seek(length - 2, 1)
    raise BadHeader(f"its JPEG data has no frame header (SOF) in its first {_MAX_RECORDS} "
                    "segments")


def _exr(f: BinaryIO, version: int) -> ImageHeader:
    """Attributes (name, type, size, value) up to an empty name; a multi-part file has one
    such header per part, ended by another empty name. The largest part counts."""
    parts, records = [], 0
    while True:
        window, channels, sample_bytes = None, 0, 0
        first = True
        while True:
            records += 1
            if records > _MAX_RECORDS:
                raise BadHeader(f"its OpenEXR header has more than {_MAX_RECORDS} attributes")
            name = _c_string(f)
            if not name:
                break
            first = False
            kind = _c_string(f)
            (size,) = struct.unpack("<i", _exactly(f, 4))
            if size < 0:
                raise BadHeader(f"its OpenEXR attribute '{name}' has size {size}")
            if name == "dataWindow" and kind == "box2i":
                if size != 16:
                    raise BadHeader(f"its OpenEXR dataWindow has size {size}, expected 16")
                window = struct.unpack("<iiii", _exactly(f, 16))
            elif name == "channels" and kind == "chlist":
                channels, sample_bytes = _chlist(_exactly(f, size))
            else:
                f.seek(size, 1)
        if first and parts:  # the empty header that ends a multi-part file
            break
        if window is None:
            raise BadHeader("its OpenEXR header has no dataWindow")
        x0, y0, x1, y1 = window
        parts.append(ImageHeader("OpenEXR", x1 - x0 + 1, y1 - y0 + 1, channels, sample_bytes))
        if not version & _EXR_MULTIPART:
            break
    return max(parts, key=lambda h: h.pixels * max(h.sample_bytes, 1))


def _chlist(data: bytes) -> tuple[int, int]:
    """Channel count and bytes per pixel of all channels of a ``chlist`` value."""
    count = size = at = 0
    while at < len(data) and data[at] != 0:
        end = data.find(b"\0", at)
        if end < 0 or end + 17 > len(data):
            raise BadHeader("its OpenEXR channel list is truncated")
        (kind,) = struct.unpack("<i", data[end + 1:end + 5])
        if kind not in _EXR_SAMPLE_BYTES:
            raise BadHeader(f"its OpenEXR channel '{data[at:end].decode(errors='replace')}' has "
                            f"pixel type {kind}")
        count, size, at = count + 1, size + _EXR_SAMPLE_BYTES[kind], end + 17
    return count, size


def _c_string(f: BinaryIO) -> str:
    """A NUL-terminated name, read in one go and the rest given back."""
    data = f.read(_EXR_MAX_NAME + 1)
    end = data.find(b"\0")
    if end < 0:
        raise BadHeader("its header is truncated" if len(data) <= _EXR_MAX_NAME else
                        f"its OpenEXR header has a name longer than {_EXR_MAX_NAME} bytes")
    f.seek(end + 1 - len(data), 1)
    return data[:end].decode("ascii", errors="replace")
