import json
import re
import struct
import time
import uuid

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robot_link.protocol import (
    HEADER,
    MAGIC,
    Message,
    MessageType,
    ProtocolError,
    decode_message,
    encode_message,
)
from tests.media import depth_png, jpeg

SID = uuid.UUID("12345678-1234-5678-1234-567812345678")
JPEG = jpeg(640, 480)
PNG = depth_png(224, 172)
DEPTH = {
    "encoding": "png16_depth_mm",
    "width": 224,
    "height": 172,
    "fx": 1,
    "fy": 1,
    "cx": 0,
    "cy": 0,
}


def raw(
    mtype: int,
    meta: object,
    payload: bytes = b"",
    *,
    magic: bytes = MAGIC,
    version: int = 1,
    flags: int = 0,
    seq: int = 1,
) -> bytes:
    m = json.dumps(meta).encode()
    return (
        HEADER.pack(magic, version, mtype, flags, SID.bytes, seq, time.time(), len(m)) + m + payload
    )


@pytest.mark.parametrize(
    "mtype, meta, payload",
    [
        (
            MessageType.SESSION_START,
            {"structure": "G3", "operator": "ana", "calibration": {"camera": {"px_per_m": 3555.5}}},
            b"",
        ),
        (
            MessageType.FRAME,
            {
                "encoding": "jpeg",
                "width": 640,
                "height": 480,
                "pose": {"x": 0.1, "y": 0.2, "yaw": 0.3},
            },
            JPEG,
        ),
        (
            MessageType.CLOUD,
            {
                "encoding": "png16_depth_mm",
                "width": 224,
                "height": 172,
                "fx": 195.0,
                "fy": 195.0,
                "cx": 111.5,
                "cy": 85.5,
            },
            PNG,
        ),
        (
            MessageType.CLOUD,
            {"encoding": "xyz_f32", "width": 2, "height": 1},
            struct.pack("<6f", 1, 2, 3, 4, 5, 6),
        ),
        (
            MessageType.TELEMETRY,
            {"ir_range_m": [0.03, 0.03, 0.03, 0.5], "battery_v": {"main": 12.1}},
            b"",
        ),
        (MessageType.COMMAND, {"cmd": "drive", "args": {"v": 0.1}}, b""),
        (MessageType.ACK, {"status": "stored", "of": "FRAME"}, b""),
        (MessageType.SESSION_END, {"reason": "done", "frames": 3, "clouds": 3}, b""),
    ],
)
def test_roundtrip_keeps_every_field(mtype: MessageType, meta: dict, payload: bytes) -> None:
    msg = Message(mtype, SID, 42, 1700000000.5, meta, payload)
    out = decode_message(encode_message(msg))
    assert (out.type, out.session_id, out.seq, out.timestamp, out.payload) == (
        mtype,
        SID,
        42,
        1700000000.5,
        payload,
    )
    for key, value in meta.items():
        assert out.meta[key] == value


def _meta_bytes(mtype: int, meta: bytes) -> bytes:
    """A message whose meta is exactly these bytes."""
    return HEADER.pack(MAGIC, 1, mtype, 0, SID.bytes, 1, time.time(), len(meta)) + meta


@pytest.mark.parametrize(
    "data, fragment",
    [
        (b"", "shorter than"),
        (b"STLS\x01", "shorter than"),
        (raw(5, {}, magic=b"XXXX"), "bad magic"),
        (raw(5, {}, version=9), "version 9"),
        (raw(77, {}), "unknown message type 77"),
        (raw(5, {}, flags=1), "flags"),
        (raw(5, [1, 2]), "JSON object"),
        (HEADER.pack(MAGIC, 1, 5, 0, SID.bytes, 1, 0.0, 4) + b"{no}", "not valid UTF-8 JSON"),
        (HEADER.pack(MAGIC, 1, 5, 0, SID.bytes, 1, 0.0, 999) + b"{}", "does not fit"),
        (raw(3, {"width": 640, "height": 480}, b"GIF89a"), "not a JPEG"),
        (raw(3, {"width": -1, "height": 480}, JPEG), "width"),
        (
            raw(4, {"encoding": "xyz_f32", "width": 3, "height": 1}, b"\x00" * 12),
            "expected width*height*12",
        ),
        (raw(4, {"encoding": "png16_depth_mm", "width": 224, "height": 172}, PNG), "needs fx"),
        (raw(3, {"width": 64, "height": 48}, JPEG), "JPEG is 640×480, meta says 64×48"),
        (raw(3, {"width": 640, "height": 480}, JPEG[:2] + b"\xff\xda" + JPEG[2:]), "no frame"),
        (raw(3, {"width": 9000, "height": 9000}, JPEG), "40,000,000 pixels"),
        (raw(4, {**DEPTH, "width": 4000, "height": 4000}, PNG), "4,000,000 pixels"),
        (raw(4, {**DEPTH, "width": 2000, "height": 1000}, PNG), "224×172, meta says 2000×1000"),
        (
            raw(4, DEPTH, cv2.imencode(".png", np.zeros((172, 224), np.uint8))[1].tobytes()),
            "16-bit",
        ),
        (raw(5, {}, b"junk"), "carry no payload"),
        (raw(6, {"cmd": "self_destruct"}), "cmd"),
        (raw(5, {"x": 2**64}, seq=2**63), "2**63"),
        (_meta_bytes(5, b'{"x":' + b"[" * 600 + b"]" * 600 + b"}"), "cannot be stored"),
        (_meta_bytes(5, b'{"x":' + b"[" * 5000 + b"]" * 5000 + b"}"), "nested too deeply"),
        (_meta_bytes(5, b'{"x":' + b"7" * 5000 + b"}"), "out of range"),
        (_meta_bytes(5, b'{"note": "G3 \\ud800"}'), "lone UTF-16 surrogate"),
        (_meta_bytes(5, b'{"note": "G3\\u0000"}'), "NUL character"),
        (_meta_bytes(1, b'{"structure": "span", "extra": {"k\\u0000": 1}}'), "NUL character"),
    ],
    ids=lambda v: v if isinstance(v, str) else "",  # named by the error (the bytes hold a time)
)
def test_malformed_messages_get_a_clear_error(data: bytes, fragment: str) -> None:
    with pytest.raises(ProtocolError, match=re.escape(fragment)):
        decode_message(data)


def test_oversized_message_is_rejected_before_parsing() -> None:
    data = raw(3, {"width": 1, "height": 1}, JPEG + b"\x00" * 2000)
    with pytest.raises(ProtocolError, match="more than the limit"):
        decode_message(data, max_bytes=1000)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_decoder_raises_only_protocol_errors_on_random_bytes(data: bytes) -> None:
    try:
        decode_message(data)
    except ProtocolError:
        pass


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=120), st.integers(0, 255), st.integers(0, 300))
def test_decoder_survives_mutated_valid_messages(tail: bytes, byte: int, pos: int) -> None:
    good = bytearray(
        encode_message(
            Message(MessageType.FRAME, SID, 7, 1.0, {"width": 4, "height": 4}, jpeg(4, 4))
        )
    )
    good[pos % len(good)] = byte
    try:
        decode_message(bytes(good) + tail)
    except ProtocolError:
        pass
