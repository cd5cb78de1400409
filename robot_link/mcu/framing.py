"""Frames on the serial line: ``COBS(type | seq | body | CRC-16) 0x00``.

COBS (Consistent Overhead Byte Stuffing) removes every zero byte from a frame, so a single
``0x00`` marks its end and a receiver that starts mid-stream or loses bytes finds the next
frame at the next zero. The CRC is CRC-16/XMODEM (polynomial 0x1021, initial 0), big-endian,
over type, seq and body.
"""

from __future__ import annotations

from dataclasses import dataclass

from cobs import cobs
from crc import Calculator, Crc16

_CRC = Calculator(Crc16.XMODEM, optimized=True)  # type: ignore[arg-type]  # the package types its configs loosely
MAX_FRAME = 1024  # bytes before COBS; longer runs without a delimiter are noise


def crc16(data: bytes) -> int:
    """CRC-16/XMODEM of ``data``."""
    return int(_CRC.checksum(data))


@dataclass(frozen=True)
class Frame:
    """One decoded frame."""

    type: int
    seq: int
    body: bytes


def encode_frame(ptype: int, seq: int, body: bytes = b"") -> bytes:
    """The bytes that carry one frame on the line, delimiter included."""
    raw = bytes([ptype & 0xFF, seq & 0xFF]) + body
    if len(raw) + 2 > MAX_FRAME:
        raise ValueError(f"frame of {len(raw) + 2} bytes exceeds {MAX_FRAME}")
    return cobs.encode(raw + crc16(raw).to_bytes(2, "big")) + b"\x00"


class FrameError(ValueError):
    """A frame that arrived damaged."""


def decode_frame(stuffed: bytes) -> Frame:
    """The frame in ``stuffed`` (COBS bytes without the delimiter); FrameError if damaged."""
    try:
        raw = cobs.decode(stuffed)
    except cobs.DecodeError as exc:
        raise FrameError(f"bad COBS encoding: {exc}") from None
    if len(raw) < 4:
        raise FrameError(f"frame of {len(raw)} bytes is too short")
    if crc16(raw[:-2]) != int.from_bytes(raw[-2:], "big"):
        raise FrameError("CRC mismatch")
    return Frame(raw[0], raw[1], raw[2:-2])


class FrameReader:
    """Splits a byte stream into frames; damaged frames come out as :class:`FrameError`."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[Frame | FrameError]:
        """Frames (or their errors) completed by ``data``, in order."""
        out: list[Frame | FrameError] = []
        self._buf += data
        while True:
            end = self._buf.find(0)
            if end < 0:
                if len(self._buf) > 2 * MAX_FRAME:
                    out.append(FrameError(f"{len(self._buf)} bytes without a delimiter"))
                    self._buf.clear()
                return out
            chunk = bytes(self._buf[:end])
            del self._buf[: end + 1]
            if not chunk:
                continue  # idle delimiters between frames
            try:
                out.append(decode_frame(chunk))
            except FrameError as exc:
                out.append(exc)
