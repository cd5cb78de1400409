"""A PNG encoded in segments of rows, each on its own (any worker, any order), then joined
by concatenation: pigz's parallel deflate applied to a PNG's image data.

A segment's rows are Sub-filtered (PNG filter type 1: each byte minus the same channel of
the pixel to its left, so a segment needs no row of another) and deflated alone, ending
in a sync flush (byte-aligned, no final block). Deflate streams of consecutive segments
so concatenate into one stream (back-references never cross a segment). A segment's file
holds a header (first row, rows, the Adler-32 and length of its filtered bytes) and its
IDAT chunk, CRC included. :func:`join_segments` writes the signature and IHDR, the zlib
header, the segments' IDAT chunks in row order, an empty final block with the whole
stream's Adler-32 (combined from the segments' as zlib's ``adler32_combine`` does) and
IEND: copying, no compression.

Sub-filtered deflate at level 1 is faster than the full image through libvips (deflate
level 3, no filter) and gives smaller files on mosaics (``docs/benchmarks.md``).
"""

from __future__ import annotations

import os
import struct
import uuid
import zlib
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from server.storage.write_behind import WriteBehind

SIGNATURE = b"\x89PNG\r\n\x1a\n"
LEVEL = 1  # deflate level: with the Sub filter, higher levels cost 2x for 5 % smaller files
_HEADER = struct.Struct(">QQIQ")  # first row, rows, Adler-32, filtered bytes
_ZLIB_HEADER = b"\x78\x01"  # deflate, 32 KiB window, fastest level; (0x7801 % 31 == 0)
_EMPTY_FINAL_BLOCK = b"\x03\x00"  # a final fixed-Huffman block holding nothing
_ADLER_BASE = 65521


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def sub_filtered(rows: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Rows (H, W) or (H, W, C) as PNG's Sub-filtered scanlines, (H, 1 + W·C): the filter
    byte 1, then each byte minus the byte C before it (modulo 256)."""
    h = rows.shape[0]
    flat = np.ascontiguousarray(rows).reshape(h, -1)
    c = 1 if rows.ndim == 2 else rows.shape[2]
    out = np.empty((h, flat.shape[1] + 1), np.uint8)
    out[:, 0] = 1
    out[:, 1 : 1 + c] = flat[:, :c]
    np.subtract(flat[:, c:], flat[:, :-c], out=out[:, 1 + c :])
    return out


def encode_segment(y0: int, rows: NDArray[np.uint8], level: int = LEVEL) -> bytes:
    """The segment file's bytes for ``rows`` ((H, W) or (H, W, C) uint8) starting at image
    row ``y0``: header and IDAT chunk."""
    scanlines = sub_filtered(rows)
    compressor = zlib.compressobj(level, zlib.DEFLATED, -15)
    data = compressor.compress(scanlines.data) + compressor.flush(zlib.Z_SYNC_FLUSH)
    header = _HEADER.pack(y0, rows.shape[0], zlib.adler32(scanlines.data), scanlines.nbytes)
    return header + _chunk(b"IDAT", data)


def write_segment(folder: Path, y0: int, rows: NDArray[np.uint8], level: int = LEVEL) -> Path:
    """Encode ``rows`` (from image row ``y0``) into ``folder`` as one segment, atomically (a
    part run again, or twice by workers that lost and took over a lease, replaces it whole)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{y0:010d}.seg"
    tmp = folder / f".{y0:010d}.{uuid.uuid4().hex}.tmp"
    tmp.write_bytes(encode_segment(y0, rows, level))
    os.replace(tmp, path)
    return path


def adler32_combine(adler1: int, adler2: int, length2: int) -> int:
    """Adler-32 of A + B from Adler-32 of A, of B and the length of B (zlib's adler32.c)."""
    rem = length2 % _ADLER_BASE
    sum1 = adler1 & 0xFFFF
    sum2 = (rem * sum1) % _ADLER_BASE
    sum1 += (adler2 & 0xFFFF) + _ADLER_BASE - 1
    sum2 += (adler1 >> 16) + (adler2 >> 16) + _ADLER_BASE - rem
    sum1 %= _ADLER_BASE
    sum2 %= _ADLER_BASE
    return (sum2 << 16) | sum1


def join_segments(folder: Path, out: Path, width: int, height: int, channels: int) -> None:
    """Write the PNG ``out`` (``width`` × ``height``, 1 or 3 ``channels``) from the segments
    in ``folder``; a ValueError names the rows no segment holds (or holds twice)."""
    if channels not in (1, 3):
        raise ValueError(f"a PNG segment image has 1 or 3 channels, not {channels}")
    segments = []
    for path in sorted(folder.glob("*.seg")):
        with path.open("rb") as fh:
            segments.append((*_HEADER.unpack(fh.read(_HEADER.size)), path))
    row, adler = 0, 1
    for y0, rows, checksum, length, path in segments:
        if y0 != row:
            raise ValueError(f"PNG segments: rows {row}-{y0 - 1} missing or overlapping")
        row += rows
        adler = adler32_combine(adler, checksum, length)
    if row != height:
        raise ValueError(f"PNG segments hold {row} rows, the image has {height}")
    tmp = out.with_name(f".{out.name}.tmp")
    colour = 0 if channels == 1 else 2
    with WriteBehind(tmp) as fh:
        fh.write(SIGNATURE)
        fh.write(_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, colour, 0, 0, 0)))
        fh.write(_chunk(b"IDAT", _ZLIB_HEADER))
        for *_, path in segments:
            with path.open("rb") as seg:
                seg.seek(_HEADER.size)
                while block := seg.read(1 << 22):
                    fh.write(block)
        fh.write(_chunk(b"IDAT", _EMPTY_FINAL_BLOCK + struct.pack(">I", adler)))
        fh.write(_chunk(b"IEND", b""))
    os.replace(tmp, out)
