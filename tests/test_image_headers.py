"""Image dimensions from headers alone: crafted PNG, JPEG and OpenEXR bytes, broken ones named
by file. No daemon, no decoder."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest

from matoptd.server.image_headers import BadHeader, read_header

from scenes import exr, png


def header(data: bytes, name: str = "ref.img"):
    return read_header(io.BytesIO(data), name)


def png_header_only(width: int, height: int, colour: int = 2, depth: int = 8) -> bytes:
    """A PNG that is nothing but its IHDR: what a 600 KB file decoding to 25000x25000 px looks
    like to a header reader."""
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr
            + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr)))


def segment(marker: int, payload: bytes) -> bytes:
    return bytes([0xFF, marker]) + struct.pack(">H", len(payload) + 2) + payload


def jpeg(width: int, height: int, sof: int = 0xC0, components: int = 3,
         precision: int = 8) -> bytes:
    """SOI, a JFIF APP0, a quantization table, fill bytes, the frame header, then the scan."""
    return (b"\xff\xd8" + segment(0xE0, b"JFIF\0\x01\x01\0\0\x01\0\x01\0\0")
            + segment(0xDB, bytes(65)) + b"\xff\xff"
            + segment(sof, struct.pack(">BHHB", precision, height, width, components)
                      + bytes(3 * components))
            + segment(0xDA, bytes(10)) + b"\x00" * 32 + b"\xff\xd9")


def exr_attribute(name: str, kind: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value


def test_png_dimensions_and_layout():
    h = header(png(np.zeros((3, 5, 3))), "small.png")
    assert (h.format, h.width, h.height, h.channels, h.sample_bytes) == ("PNG", 5, 3, 3, 3)
    big = header(png_header_only(25000, 25000, colour=6, depth=16))
    assert (big.width, big.height, big.channels, big.sample_bytes) == (25000, 25000, 4, 8)
    # RGBA 16-bit, then float RGB: what decoding it would take.
    assert big.decoded_bytes == 25000 * 25000 * (8 + 12)


@pytest.mark.parametrize("sof", [0xC0, 0xC2, 0xC1, 0xCF])
def test_jpeg_dimensions_from_any_frame_header(sof):
    h = header(jpeg(640, 480, sof), "photo.jpg")
    assert (h.format, h.width, h.height, h.channels, h.sample_bytes) == ("JPEG", 640, 480, 3, 3)


def test_jpeg_twelve_bit_grey():
    h = header(jpeg(100, 20, components=1, precision=12))
    assert (h.channels, h.sample_bytes) == (1, 2)


def test_exr_dimensions_from_data_window():
    h = header(exr(np.zeros((4, 9, 3))), "linear.exr")
    assert (h.format, h.width, h.height, h.channels, h.sample_bytes) == ("OpenEXR", 9, 4, 3, 12)


def test_exr_data_window_need_not_start_at_zero():
    channels = b"".join(c + b"\0" + struct.pack("<iB3xii", 1, 0, 1, 1) for c in (b"A", b"Y"))
    data = (b"\x76\x2f\x31\x01" + struct.pack("<I", 2)
            + exr_attribute("comments", "string", b"x" * 5000)  # skipped, not read
            + exr_attribute("channels", "chlist", channels + b"\0")
            + exr_attribute("dataWindow", "box2i", struct.pack("<iiii", -10, 5, 89, 24))
            + b"\0")
    h = header(data)
    assert (h.width, h.height, h.channels, h.sample_bytes) == (100, 20, 2, 4)


def test_exr_multipart_counts_its_largest_part():
    def part(w: int, h: int) -> bytes:
        return (exr_attribute("name", "string", f"part{w}".encode())
                + exr_attribute("dataWindow", "box2i", struct.pack("<iiii", 0, 0, w - 1, h - 1))
                + b"\0")
    data = b"\x76\x2f\x31\x01" + struct.pack("<I", 2 | 0x1000) + part(8, 8) + part(300, 200) \
        + part(16, 4) + b"\0"
    h = header(data)
    assert (h.width, h.height) == (300, 200)


@pytest.mark.parametrize("data,why", [
    (b"GIF89a\x01\x00\x01\x00", "not a PNG, JPEG or OpenEXR file"),
    (b"", "not a PNG, JPEG or OpenEXR file"),
    (png_header_only(10, 10)[:20], "its header is truncated"),
    (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IDAT" + bytes(17),
     "its PNG header has no IHDR chunk first"),
    (png_header_only(10, 10, colour=5), "colour type 5"),
    (png_header_only(0, 10), "gives a size of 0x10 pixels"),
    (jpeg(64, 64)[:30], "its header is truncated"),
    (b"\xff\xd8" + segment(0xDB, bytes(65)) + segment(0xDA, bytes(4)),
     "no frame header (SOF) before the image data"),
    (b"\xff\xd8\x00\x00", "a marker was expected"),
    (b"\xff\xd8" + segment(0xE1, bytes(10)) * 5000, "no frame header (SOF) in its first 4096"),
    (jpeg(64, 0), "gives a size of 64x0 pixels"),
    (exr(np.zeros((2, 2, 3)))[:60], "its header is truncated"),
    (b"\x76\x2f\x31\x01" + struct.pack("<I", 2) + exr_attribute("owner", "string", b"me")
     + b"\0", "no dataWindow"),
    (b"\x76\x2f\x31\x01" + struct.pack("<I", 2)
     + exr_attribute("dataWindow", "box2i", struct.pack("<iiii", 0, 0, -5, 3)) + b"\0",
     "gives a size of -4x4 pixels"),
    (b"\x76\x2f\x31\x01" + struct.pack("<I", 2) + b"n" * 400, "name longer than 255 bytes"),
    (b"\x76\x2f\x31\x01" + struct.pack("<I", 2) + exr_attribute("a", "int", b"1234") * 5000,
     "more than 4096 attributes"),
])
def test_broken_or_foreign_headers_name_the_file(data, why):
    with pytest.raises(BadHeader) as err:
        header(data, "holiday.png")
    assert "reference image 'holiday.png' cannot be read" in str(err.value)
    assert why in str(err.value)
