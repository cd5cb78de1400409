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

Before the image data the PNG carries its segments' index (a private ancillary chunk,
``sgIX``, which decoders skip): each segment's first row, rows, file offset and Adler-32.
Since no segment needs another, :func:`read_rows` decodes any run of rows from the PNG
alone, on any worker, without the rows above it.

Sub-filtered deflate at ISA-L's level 1 (:mod:`isal`: zlib's format, several times its
speed) is faster than the full image through libvips (deflate level 3, no filter) and gives
smaller files on mosaics (``docs/benchmarks.md``).
"""

from __future__ import annotations

import os
import struct
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
from isal import isal_zlib as zlib  # zlib's formats, ISA-L's speed
from numpy.typing import NDArray

from server.storage.write_behind import CALL_BYTES, WriteBehind, read_up_to, write_file_behind

SIGNATURE = b"\x89PNG\r\n\x1a\n"
LEVEL = 1  # ISA-L's levels (0-3): 5x faster than zlib's level 1 with smaller files on mosaics
_HEADER = struct.Struct(">QQIQ")  # first row, rows, Adler-32, filtered bytes
_ZLIB_HEADER = b"\x78\x01"  # deflate, 32 KiB window, fastest level; (0x7801 % 31 == 0)
_EMPTY_FINAL_BLOCK = b"\x03\x00"  # a final fixed-Huffman block holding nothing
_ADLER_BASE = 65521
_INDEX = b"sgIX"  # ancillary, private, unsafe to copy: it describes the IDAT chunks' layout
_ENTRY = struct.Struct(">IIQI")  # first row, rows, offset of the IDAT chunk, Adler-32
_IHDR = struct.Struct(">IIBBBBB")


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
    write_file_behind(tmp, encode_segment(y0, rows, level))
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
    at = len(SIGNATURE) + 12 + _IHDR.size + 12 + _ENTRY.size * len(segments)
    at += 12 + len(_ZLIB_HEADER)
    entries = []
    for y0, rows, checksum, _, path in segments:
        entries.append(_ENTRY.pack(y0, rows, at, checksum))
        at += path.stat().st_size - _HEADER.size
    index = b"".join(entries)
    with WriteBehind(tmp) as fh:
        fh.write(SIGNATURE)
        fh.write(_chunk(b"IHDR", _IHDR.pack(width, height, 8, colour, 0, 0, 0)))
        fh.write(_chunk(_INDEX, index))
        fh.write(_chunk(b"IDAT", _ZLIB_HEADER))
        for *_, path in segments:
            with path.open("rb") as seg:
                seg.seek(_HEADER.size)
                while block := seg.read(CALL_BYTES):
                    fh.write(block)
        fh.write(_chunk(b"IDAT", _EMPTY_FINAL_BLOCK + struct.pack(">I", adler)))
        fh.write(_chunk(b"IEND", b""))
    os.replace(tmp, out)


@dataclass(frozen=True)
class _Index:
    width: int
    height: int
    channels: int
    entries: list[tuple[int, int, int, int]]  # first row, rows, IDAT chunk offset, Adler-32


def _index(fh: BinaryIO) -> _Index | None:
    """The segment index of the PNG open in ``fh``; None for a PNG without one."""
    size = len(SIGNATURE) + 12 + _IHDR.size + 8  # signature, IHDR, the next chunk's head
    head = fh.read(size)
    if len(head) < size or head[:8] != SIGNATURE:
        return None
    width, height, depth, colour, *_ = _IHDR.unpack_from(head, 16)
    length, kind = struct.unpack_from(">I4s", head, 16 + _IHDR.size + 4)
    if kind != _INDEX or depth != 8 or colour not in (0, 2):
        return None
    entries = list(_ENTRY.iter_unpack(fh.read(length)))
    return _Index(width, height, 1 if colour == 0 else 3, entries)


def segment_rows(png: Path) -> list[tuple[int, int]] | None:
    """The row ranges (y0, y1) of a PNG's segments, in order; None for a PNG without a
    segment index (written by another tool)."""
    with png.open("rb") as fh:
        index = _index(fh)
    return None if index is None else [(y0, y0 + n) for y0, n, *_ in index.entries]


def read_rows(png: Path, y0: int, y1: int) -> NDArray[np.uint8] | None:
    """Rows ``y0:y1`` of a PNG joined by :func:`join_segments`, (y1 - y0, W) or
    (y1 - y0, W, 3), decoded from the segments that hold them only; None for a PNG without
    a segment index (written by another tool). A ValueError names a damaged segment."""
    with png.open("rb") as fh:
        index = _index(fh)
        if index is None:
            return None
        width, channels = index.width, index.channels
        y0, y1 = max(0, y0), min(index.height, y1)
        stride = 1 + width * channels
        pieces = []
        for first, rows, offset, checksum in index.entries:
            if first >= y1 or first + rows <= y0:
                continue
            fh.seek(offset)
            size, kind = struct.unpack(">I4s", fh.read(8))
            last = first + rows - 1
            try:  # a segment has no final block: the empty one ends it
                raw = read_up_to(fh, size) + _EMPTY_FINAL_BLOCK if kind == b"IDAT" else b""
                data = zlib.decompress(raw, -15, rows * stride) if raw else b""
            except zlib.error:
                data = b""  # damaged: named below
            if len(data) != rows * stride or zlib.adler32(data) != checksum:
                raise ValueError(f"{png.name}: the segment of rows {first}-{last} is damaged")
            lines = np.frombuffer(data, np.uint8).reshape(rows, stride)
            if np.any(lines[:, 0] != 1):
                raise ValueError(f"{png.name}: rows {first}-{last} are not Sub-filtered")
            a, b = max(y0, first) - first, min(y1, first + rows) - first
            sub = lines[a:b, 1:].reshape(b - a, width, channels)
            pieces.append(np.cumsum(sub, axis=1, dtype=np.uint8))  # undo Sub, modulo 256
    out = np.concatenate(pieces) if pieces else np.zeros((0, width, channels), np.uint8)
    if out.shape[0] != max(0, y1 - y0):
        raise ValueError(f"{png.name}: the segment index does not cover rows {y0}-{y1 - 1}")
    return out[:, :, 0] if channels == 1 else out
