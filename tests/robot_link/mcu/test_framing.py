"""Frames on the serial line: COBS removes every zero, the CRC catches damage, and a reader
that starts mid-stream or loses bytes finds the next frame."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from robot_link.mcu.framing import (
    MAX_FRAME,
    Frame,
    FrameError,
    FrameReader,
    crc16,
    decode_frame,
    encode_frame,
)


def test_crc16_is_xmodem() -> None:
    assert crc16(b"123456789") == 0x31C3  # the catalogue's check value


@given(st.integers(0, 255), st.integers(0, 255), st.binary(max_size=MAX_FRAME - 4))
def test_a_frame_comes_back_as_sent_and_holds_one_zero(ptype: int, seq: int, body: bytes) -> None:
    data = encode_frame(ptype, seq, body)
    assert data.count(0) == 1 and data.endswith(b"\x00")
    assert FrameReader().feed(data) == [Frame(ptype, seq, body)]


@given(st.binary(min_size=1, max_size=40), st.integers(0, 10_000), st.integers(1, 255))
def test_any_damaged_byte_is_caught(body: bytes, where: int, flip: int) -> None:
    data = bytearray(encode_frame(0x83, 1, body)[:-1])
    data[where % len(data)] ^= flip
    if 0 in data:  # the damage made a delimiter: the reader sees two pieces
        return
    with pytest.raises(FrameError):
        decode_frame(bytes(data))


def test_the_reader_resynchronises_after_noise_and_split_reads() -> None:
    good = encode_frame(0x82, 9, b"\x01\x00")
    stream = b"\x13\x37noise" + good[:3] + b"\x00" + good + good
    reader = FrameReader()
    out = []
    for i in range(0, len(stream), 5):  # bytes arrive in small reads
        out += reader.feed(stream[i : i + 5])
    frames = [f for f in out if isinstance(f, Frame)]
    assert frames == [Frame(0x82, 9, b"\x01\x00")] * 2
    assert any(isinstance(f, FrameError) for f in out)


def test_a_stream_without_delimiters_is_dropped_not_buffered_for_ever() -> None:
    reader = FrameReader()
    out = reader.feed(b"\x05" * (3 * MAX_FRAME))
    assert len(out) == 1 and isinstance(out[0], FrameError)
    assert reader.feed(encode_frame(1, 2, b"ok")) == [Frame(1, 2, b"ok")]


def test_an_oversized_frame_is_refused() -> None:
    with pytest.raises(ValueError, match="exceeds"):
        encode_frame(1, 1, bytes(MAX_FRAME))
