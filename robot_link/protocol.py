"""The steelscan wire protocol: one binary websocket message per robot message.

Layout (little-endian), see ``docs/protocol.md``::

    magic  "STLS"   4 bytes
    version        u8
    type           u8   (MessageType)
    flags          u16  (reserved, must be 0)
    session_id     16 bytes (UUID)
    seq            u64  (per session, assigned by the sender; below 2**63)
    timestamp      f64  (sender clock, seconds since the Unix epoch)
    meta_len       u32
    meta           meta_len bytes of UTF-8 JSON object
    payload        the rest (JPEG, depth PNG, raw float32 ... depending on type)
"""

from __future__ import annotations

import enum
import json
import math
import struct
import uuid
from dataclasses import dataclass, field
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from robot_link.image_header import PNG_SIGNATURE, ImageHeaderError, jpeg_size, png_header

PROTOCOL_VERSION = 1
MAGIC = b"STLS"
HEADER = struct.Struct("<4sBBH16sQdI")
HEADER_BYTES = HEADER.size
MAX_MESSAGE_BYTES = 8 * 1024 * 1024
# the station's answer to the websocket handshake carries its own limit, which robots obey
MAX_BYTES_HEADER = "X-Steelscan-Max-Message-Bytes"
MAX_META_BYTES = 64 * 1024
MAX_FRAME_PIXELS = 40_000_000  # a camera frame or video image (8000×5000)
MAX_CLOUD_PIXELS = 4_000_000  # a ToF depth image or organised cloud
SEQ_LIMIT = 2**63  # seq is a u64 on the wire whose top bit is clear (a signed 64-bit key)


class ProtocolError(ValueError):
    """A message that does not follow the protocol; the text says what was wrong."""


class MessageType(enum.IntEnum):
    """What a message carries."""

    SESSION_START = 1
    SESSION_END = 2
    FRAME = 3
    CLOUD = 4
    TELEMETRY = 5
    COMMAND = 6
    ACK = 7
    ERROR = 8
    COMMAND_ACK = 9
    VIDEO = 10  # live preview frame: relayed to browsers, never stored, never acknowledged


class _Meta(BaseModel):
    model_config = ConfigDict(extra="allow", frozen=True)


class Pose2D(BaseModel):
    """Odometry pose of the robot on the surface: T_world_robot as (x, y, yaw)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    x: float
    y: float
    yaw: float


class SessionStartMeta(_Meta):
    structure: str = Field(min_length=1, max_length=200)
    operator: str = Field(default="", max_length=200)
    location: str = Field(default="", max_length=200)
    robot: str = Field(default="", max_length=200)
    calibration: dict[str, Any] = Field(default_factory=dict)


class SessionEndMeta(_Meta):
    reason: str = Field(default="completed", max_length=200)
    frames: int = Field(default=0, ge=0)
    clouds: int = Field(default=0, ge=0)


class _Sized(_Meta):
    """An image's size, within a pixel budget (decoded images must fit in memory)."""

    width: int = Field(gt=0, le=16384)
    height: int = Field(gt=0, le=16384)
    _max_pixels = MAX_FRAME_PIXELS

    @model_validator(mode="after")
    def _within_budget(self) -> _Sized:
        if self.width * self.height > self._max_pixels:
            raise ValueError(f"{self.width}×{self.height} is more than {self._max_pixels:,} pixels")
        return self


class FrameMeta(_Sized):
    encoding: Literal["jpeg"] = "jpeg"
    pose: Pose2D | None = None


class CloudMeta(_Sized):
    encoding: Literal["png16_depth_mm", "xyz_f32"]
    _max_pixels = MAX_CLOUD_PIXELS
    fx: float | None = Field(default=None, gt=0)
    fy: float | None = Field(default=None, gt=0)
    cx: float | None = None
    cy: float | None = None
    pose: Pose2D | None = None


class TelemetryMeta(_Meta):
    pose: Pose2D | None = None
    wheel_speed_mps: list[float] | None = Field(default=None, min_length=4, max_length=4)
    wheel_distance_m: list[float] | None = Field(default=None, min_length=4, max_length=4)
    ir_range_m: list[float] | None = Field(default=None, min_length=4, max_length=4)
    battery_v: dict[str, float] | None = None


class VideoMeta(_Sized):
    encoding: Literal["jpeg"] = "jpeg"


# always safe: never refused, rate-limited or ignored as a replay
STOP_COMMANDS = frozenset({"stop", "estop"})
DRIVE_HOLD_S = 0.2  # a drive command holds this long; the robot stops unless a newer one arrives


class CommandMeta(_Meta):
    """An operator's command. ``drive`` args: ``linear_mps``, ``angular_radps`` (held for
    DRIVE_HOLD_S; the yaw rate about the robot's z axis, which points into the surface with
    x forward and y to its right: positive turns right); ``lift``: ``axle`` front|rear, ``up`` bool; ``auto_capture``: ``on`` bool,
    ``spacing_m``; ``sweep``: ``action`` start|pause|resume|stop (the on-board coverage
    sweep); any command may carry ``sent_ms`` (the operator's clock, ms since the epoch)."""

    cmd: Literal[
        "drive",
        "stop",
        "estop",
        "resume",
        "capture",
        "lift",
        "auto_capture",
        "sweep",
        "end_session",
    ]
    args: dict[str, Any] = Field(default_factory=dict)


class AckMeta(_Meta):
    status: Literal["stored", "duplicate"]
    of: str = ""


class ErrorMeta(_Meta):
    error: str
    retry: bool = False  # the station cannot store it yet (unknown session): resend later


class CommandAckMeta(_Meta):
    cmd: str = ""
    accepted: bool = True


META_MODELS: dict[MessageType, type[_Meta]] = {
    MessageType.SESSION_START: SessionStartMeta,
    MessageType.SESSION_END: SessionEndMeta,
    MessageType.FRAME: FrameMeta,
    MessageType.CLOUD: CloudMeta,
    MessageType.TELEMETRY: TelemetryMeta,
    MessageType.COMMAND: CommandMeta,
    MessageType.ACK: AckMeta,
    MessageType.ERROR: ErrorMeta,
    MessageType.COMMAND_ACK: CommandAckMeta,
    MessageType.VIDEO: VideoMeta,
}

JPEG_SOI = b"\xff\xd8"


@dataclass(frozen=True)
class Message:
    """One protocol message; ``meta`` is the validated JSON object."""

    type: MessageType
    session_id: uuid.UUID
    seq: int
    timestamp: float
    meta: dict[str, Any] = field(default_factory=dict)
    payload: bytes = b""


def encode_message(message: Message, *, max_bytes: int = MAX_MESSAGE_BYTES) -> bytes:
    """Serialise a message to its binary form (validating its meta, seq and size first: a
    message the station would refuse is never sent)."""
    try:  # NaN or infinity: the station refuses them
        json.dumps(message.meta, allow_nan=False, default=str)
    except ValueError:
        raise ProtocolError(NON_FINITE.format("NaN or infinity")) from None
    meta = _validate_meta(message.type, message.meta)
    meta_bytes = json.dumps(meta, separators=(",", ":")).encode()
    if len(meta_bytes) > MAX_META_BYTES:
        raise ProtocolError(f"meta is {len(meta_bytes)} bytes, more than {MAX_META_BYTES}")
    _check_seq(message.type, message.seq)
    size = HEADER_BYTES + len(meta_bytes) + len(message.payload)
    if size > max_bytes:
        raise ProtocolError(f"message is {size} bytes, more than the limit of {max_bytes}")
    header = HEADER.pack(
        MAGIC,
        PROTOCOL_VERSION,
        int(message.type),
        0,
        message.session_id.bytes,
        message.seq,
        float(message.timestamp),
        len(meta_bytes),
    )
    return header + meta_bytes + message.payload


def decode_message(data: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> Message:
    """Parse and validate one binary message; raise ProtocolError saying what is wrong."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"expected a binary message, got {type(data).__name__}")
    data = bytes(data)
    if len(data) > max_bytes:
        raise ProtocolError(f"message is {len(data)} bytes, more than the limit of {max_bytes}")
    if len(data) < HEADER_BYTES:
        raise ProtocolError(
            f"message is {len(data)} bytes, shorter than the {HEADER_BYTES}-byte header"
        )
    magic, version, type_code, flags, sid, seq, timestamp, meta_len = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError(f"bad magic {magic!r}, expected {MAGIC!r}")
    if version != PROTOCOL_VERSION:
        raise ProtocolError(
            f"protocol version {version} is not supported (expected {PROTOCOL_VERSION})"
        )
    try:
        mtype = MessageType(type_code)
    except ValueError:
        raise ProtocolError(f"unknown message type {type_code}") from None
    if flags != 0:
        raise ProtocolError(f"flags must be 0 in version {PROTOCOL_VERSION}, got {flags}")
    _check_seq(mtype, seq)
    if meta_len > MAX_META_BYTES or HEADER_BYTES + meta_len > len(data):
        raise ProtocolError(f"meta length {meta_len} does not fit in a {len(data)}-byte message")
    if not math.isfinite(timestamp) or abs(timestamp) > 1e11:
        raise ProtocolError(f"timestamp {timestamp} is not a valid time")
    raw_meta = data[HEADER_BYTES : HEADER_BYTES + meta_len]
    try:
        meta_obj = (
            json.loads(
                raw_meta.decode("utf-8"), parse_constant=_no_constant, parse_float=_finite_float
            )
            if meta_len
            else {}
        )
    except NonFiniteError as exc:
        raise ProtocolError(str(exc)) from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ProtocolError(f"meta is not valid UTF-8 JSON: {exc}") from None
    except RecursionError:
        raise ProtocolError("meta is nested too deeply") from None
    except ValueError as exc:  # an integer of more digits than Python converts
        raise ProtocolError(f"meta has a value out of range: {exc}") from None
    if not isinstance(meta_obj, dict):
        raise ProtocolError(f"meta must be a JSON object, got {type(meta_obj).__name__}")
    meta = _validate_meta(mtype, meta_obj)
    if b"\\u" in raw_meta:  # an escape may spell what no database can store as text
        try:
            json.dumps(meta, ensure_ascii=False).encode("utf-8")
        except UnicodeEncodeError:
            raise ProtocolError("meta holds a lone UTF-16 surrogate (\\ud800-\\udfff)") from None
        if b"\\u0000" in raw_meta and _holds_nul(meta):
            raise ProtocolError("meta holds a NUL character (\\u0000)")
    payload = data[HEADER_BYTES + meta_len :]
    _check_payload(mtype, meta, payload)
    return Message(mtype, uuid.UUID(bytes=sid), seq, timestamp, meta, payload)


class NonFiniteError(ValueError):
    """A NaN or infinite number in a message's meta."""


NON_FINITE = (
    "meta holds a non-finite number ({}): JSON has none; send null (or leave the field out) "
    "for a reading the robot does not have"
)


def _no_constant(name: str) -> float:
    raise NonFiniteError(NON_FINITE.format(name))


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):  # 1e999
        raise NonFiniteError(NON_FINITE.format(text))
    return value


def _holds_nul(value: Any) -> bool:
    """Whether a NUL character is in any string (key or value) of a JSON value."""
    if isinstance(value, str):
        return "\x00" in value
    if isinstance(value, dict):
        return any(_holds_nul(k) or _holds_nul(v) for k, v in value.items())
    if isinstance(value, list):
        return any(_holds_nul(v) for v in value)
    return False


def _check_seq(mtype: MessageType, seq: int) -> None:
    """A seq is below 2**63 (a signed 64-bit key); an ERROR echoes the refused message's."""
    if mtype is MessageType.ERROR:
        if not 0 <= seq < 2**64:
            raise ProtocolError(f"seq must fit in u64, got {seq}")
    elif not 0 <= seq < SEQ_LIMIT:
        raise ProtocolError(f"seq {seq} is not in [0, 2**63)")


def _validate_meta(mtype: MessageType, meta: dict[str, Any]) -> dict[str, Any]:
    try:
        model = META_MODELS[mtype].model_validate(meta)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "meta"
        raise ProtocolError(f"{mtype.name} meta field '{where}': {first['msg']}") from None
    try:
        return model.model_dump(mode="json", exclude_none=True)
    except (ValueError, RecursionError) as exc:  # nested deeper than it can be written
        raise ProtocolError(f"{mtype.name} meta cannot be stored: {exc}") from None


def _check_size(mtype: MessageType, what: str, size: tuple[int, int], meta: dict[str, Any]) -> None:
    if size != (meta["width"], meta["height"]):
        raise ProtocolError(
            f"{mtype.name} {what} is {size[0]}×{size[1]}, meta says "
            f"{meta['width']}×{meta['height']}"
        )


def _check_payload(mtype: MessageType, meta: dict[str, Any], payload: bytes) -> None:
    if mtype in (MessageType.FRAME, MessageType.VIDEO):
        if not payload.startswith(JPEG_SOI):
            raise ProtocolError(f"{mtype.name} payload is not a JPEG (missing FF D8 start marker)")
        try:
            size = jpeg_size(payload)
        except ImageHeaderError as exc:
            raise ProtocolError(f"{mtype.name} payload: {exc}") from None
        _check_size(mtype, "JPEG", size, meta)
    elif mtype is MessageType.CLOUD:
        if meta["encoding"] == "png16_depth_mm":
            if not payload.startswith(PNG_SIGNATURE):
                raise ProtocolError("CLOUD payload with encoding png16_depth_mm is not a PNG")
            try:
                png = png_header(payload)
            except ImageHeaderError as exc:
                raise ProtocolError(f"CLOUD payload: {exc}") from None
            if (png.bit_depth, png.colour_type) != (16, 0):
                raise ProtocolError(
                    f"CLOUD depth PNG must be 16-bit greyscale, got {png.bit_depth}-bit "
                    f"colour type {png.colour_type}"
                )
            _check_size(mtype, "depth PNG", (png.width, png.height), meta)
            if any(meta.get(k) is None for k in ("fx", "fy", "cx", "cy")):
                raise ProtocolError("CLOUD with a depth image needs fx, fy, cx, cy in meta")
        else:
            expected = meta["width"] * meta["height"] * 12
            if len(payload) != expected:
                raise ProtocolError(
                    f"CLOUD xyz_f32 payload is {len(payload)} bytes, expected "
                    f"width*height*12 = {expected}"
                )
    elif payload:
        raise ProtocolError(f"{mtype.name} messages carry no payload, got {len(payload)} bytes")
