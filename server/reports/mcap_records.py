"""An MCAP file's records in file order, its chunks decompressed with a bound: never more
bytes than the chunk says it holds (nor :data:`MAX_RECORD_BYTES`), whatever its compressed
stream would inflate to, so that a chunk understating its size (a decompression bomb) is
refused after the bytes it claimed, not after gigabytes."""

from __future__ import annotations

import io
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import BinaryIO

import lz4.frame
import zstandard
from mcap.records import Channel, Chunk, McapRecord, Message, Metadata
from mcap.stream_reader import StreamReader, breakup_chunk

MAX_RECORD_BYTES = 256 * 2**20  # a record (a chunk, compressed or not) read into memory
STEP = 1 << 20  # bytes decompressed at a time


class ChunkError(ValueError):
    """A chunk that does not decompress to what it says."""


def records(fh: BinaryIO) -> Iterator[McapRecord]:
    """Every record of the file, those inside chunks in their place."""
    for record in StreamReader(fh, emit_chunks=True, record_size_limit=MAX_RECORD_BYTES).records:
        if isinstance(record, Chunk):
            data = decompress(record)  # then split as an uncompressed chunk
            yield from breakup_chunk(replace(record, compression="", data=data))
        else:
            yield record


def messages(fh: BinaryIO, topics: set[str]) -> Iterator[tuple[Channel, Message] | Metadata]:
    """The messages on ``topics`` with their channel, and the metadata records, in file
    order."""
    channels: dict[int, Channel] = {}
    for record in records(fh):
        if isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is None:
                raise ChunkError(f"a message on channel {record.channel_id}, never declared")
            if channel.topic in topics:
                yield channel, record
        elif isinstance(record, Metadata):
            yield record


def decompress(chunk: Chunk) -> bytes:
    """A chunk's records, decompressed to at most its stated size (and the record bound)."""
    claimed = chunk.uncompressed_size
    if claimed > MAX_RECORD_BYTES:
        raise ChunkError(
            f"a chunk decompresses to {claimed:,} bytes, more than the {MAX_RECORD_BYTES:,} allowed"
        )
    if chunk.compression in ("", "none"):
        data = bytes(chunk.data)
    elif chunk.compression == "zstd":
        reader = zstandard.ZstdDecompressor().stream_reader(
            io.BytesIO(chunk.data), read_across_frames=True
        )
        data = _pull(lambda: reader.read(STEP), claimed)
    elif chunk.compression == "lz4":
        stream = lz4.frame.LZ4FrameDecompressor()
        first = [stream.decompress(bytes(chunk.data), max_length=STEP)]

        def more() -> bytes:
            if first:
                return first.pop()
            if stream.eof or stream.needs_input:
                return b""
            return stream.decompress(b"", max_length=STEP)

        data = _pull(more, claimed)
    else:
        raise ChunkError(f"a chunk compressed with {chunk.compression!r}, not zstd or lz4")
    if len(data) != claimed:
        raise ChunkError(
            f"a chunk says it holds {claimed:,} bytes and decompresses to "
            f"{'more' if len(data) > claimed else f'{len(data):,}'}"
        )
    return data


def _pull(read: Callable[[], bytes], claimed: int) -> bytes:
    """Decompressed bytes, a step at a time, until the stream ends or passes ``claimed``."""
    out = bytearray()
    while len(out) <= claimed:
        piece = read()
        if not piece:
            break
        out += piece
    return bytes(out)
