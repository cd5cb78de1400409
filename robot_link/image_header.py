"""Image sizes read from JPEG and PNG headers, without decoding: an image is checked against
what its message says (and against a pixel budget) before anything allocates its pixels."""

from __future__ import annotations

import struct
from dataclasses import dataclass

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# start-of-frame markers (baseline, progressive, lossless, arithmetic): they carry the size
_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_STANDALONE = frozenset(range(0xD0, 0xDA)) | {0x01}  # RSTn, SOI, EOI, TEM: no length


class ImageHeaderError(ValueError):
    """The bytes do not start like the image they claim to be."""


@dataclass(frozen=True)
class PngHeader:
    width: int
    height: int
    bit_depth: int
    colour_type: int  # 0 grey, 2 RGB, 3 palette, 4 grey+alpha, 6 RGBA


def jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a JPEG's start-of-frame segment."""
    if not data.startswith(b"\xff\xd8"):
        raise ImageHeaderError("not a JPEG (no FF D8 start marker)")
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            raise ImageHeaderError(f"JPEG marker expected at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in _STANDALONE:
            i += 2
            continue
        (length,) = struct.unpack_from(">H", data, i + 2)
        if length < 2:
            raise ImageHeaderError(f"JPEG segment of length {length} at byte {i}")
        if marker in _SOF:
            if i + 9 > n:
                break
            height, width = struct.unpack_from(">HH", data, i + 5)
            if width == 0 or height == 0:
                raise ImageHeaderError("JPEG declares an empty image")
            return width, height
        if marker == 0xDA:  # image data before any frame header
            break
        i += 2 + length
    raise ImageHeaderError("JPEG has no frame header (SOF) giving its size")


def png_header(data: bytes) -> PngHeader:
    """Size, bit depth and colour type from a PNG's IHDR chunk."""
    if not data.startswith(PNG_SIGNATURE) or len(data) < 29 or data[12:16] != b"IHDR":
        raise ImageHeaderError("not a PNG (no signature and IHDR chunk)")
    width, height, depth, colour = struct.unpack_from(">IIBB", data, 16)
    if width == 0 or height == 0:
        raise ImageHeaderError("PNG declares an empty image")
    return PngHeader(width, height, depth, colour)


def image_size(data: bytes) -> tuple[int, int]:
    """(width, height) of a JPEG or PNG."""
    if data.startswith(PNG_SIGNATURE):
        h = png_header(data)
        return h.width, h.height
    return jpeg_size(data)


def check_pixels(data: bytes, max_pixels: int, name: str = "image") -> tuple[int, int]:
    """The image's (width, height) if it has at most ``max_pixels``; ImageHeaderError if
    it is larger (a decompression bomb) or has no readable header."""
    width, height = image_size(data)
    if width * height > max_pixels:
        raise ImageHeaderError(
            f"{name} declares {width}×{height} pixels, more than the {max_pixels:,} allowed"
        )
    return width, height
