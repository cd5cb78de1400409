"""The packets of the MCU serial protocol, version 1 (docs/robot.md, "Serial protocol").

Little-endian fixed layouts; every packet travels in one frame (:mod:`.framing`). The host
numbers its commands with ``seq`` (0-255, wrapping) and the MCU answers each with an ACK
carrying that number; the MCU numbers its own packets so the host can count lost ones.
"""

from __future__ import annotations

import enum
import json
import struct
from dataclasses import dataclass, field
from typing import Any

PROTOCOL_VERSION = 1


class PacketType(enum.IntEnum):
    """Packet type codes: 0x0_ host to MCU, 0x8_ MCU to host."""

    HELLO = 0x01
    DRIVE = 0x02
    LIFT = 0x03
    STOP = 0x04
    ESTOP = 0x05
    RESET_ESTOP = 0x06
    HELLO_REPLY = 0x81
    ACK = 0x82
    SENSORS = 0x83
    FAULT = 0x84


class AckStatus(enum.IntEnum):
    """Why the MCU refused a command (0: carried out)."""

    OK = 0
    ESTOP_LATCHED = 1
    LOW_BATTERY = 2
    ADHESION = 3
    BAD_ARGUMENT = 4
    UNKNOWN_TYPE = 5
    WRONG_VERSION = 6
    OFF_PLATE = 7


class Fault(enum.IntFlag):
    """Fault bits of a SENSORS packet."""

    NONE = 0
    LOW_BATTERY = 0x01
    ADHESION = 0x02
    OVERCURRENT = 0x04
    EDGE = 0x08
    DEADMAN = 0x10
    ESTOP = 0x20
    OFF_PLATE = 0x40
    HOST_GARBLED = 0x80


class Flag(enum.IntFlag):
    """State bits of a SENSORS packet."""

    NONE = 0
    ESTOP_LATCHED = 0x01
    MOVING = 0x02
    FRONT_LIFT_UP = 0x04
    REAR_LIFT_UP = 0x08
    DEADMAN_STOPPED = 0x10
    BLOCKED_FORWARD = 0x20
    BLOCKED_REVERSE = 0x40


_HELLO = struct.Struct("<B")
_DRIVE = struct.Struct("<hhH")
_LIFT = struct.Struct("<BB")
_HELLO_REPLY = struct.Struct("<BH")
_ACK = struct.Struct("<BB")
_SENSORS = struct.Struct("<I4i4H2H4hHB")
_FAULT = struct.Struct("<H")


class PacketError(ValueError):
    """A frame whose body does not fit its packet type."""


@dataclass(frozen=True)
class Drive:
    """Wheel speeds (m/s, left and right side) to hold for ``hold_s`` seconds at most."""

    left_mps: float
    right_mps: float
    hold_s: float

    def pack(self) -> bytes:
        """The DRIVE body: mm/s per side and the hold in ms."""
        return _DRIVE.pack(
            _clamp_i16(round(self.left_mps * 1000)),
            _clamp_i16(round(self.right_mps * 1000)),
            max(0, min(0xFFFF, round(self.hold_s * 1000))),
        )

    @classmethod
    def unpack(cls, body: bytes) -> Drive:
        """A DRIVE body read back."""
        left, right, hold = _unpack(_DRIVE, body, "DRIVE")
        return cls(left / 1000, right / 1000, hold / 1000)


@dataclass(frozen=True)
class Lift:
    """Raise (``up``) or lower an axle's lift (paper §2: the wheels' lift for transitions)."""

    axle: str  # "front" or "rear"
    up: bool

    def pack(self) -> bytes:
        """The LIFT body."""
        return _LIFT.pack(0 if self.axle == "front" else 1, int(self.up))

    @classmethod
    def unpack(cls, body: bytes) -> Lift:
        """A LIFT body read back."""
        axle, up = _unpack(_LIFT, body, "LIFT")
        if axle > 1:
            raise PacketError(f"LIFT axle {axle} is neither 0 (front) nor 1 (rear)")
        return cls("front" if axle == 0 else "rear", bool(up))


@dataclass(frozen=True)
class HelloReply:
    """The MCU's answer to HELLO: its protocol version, sensor rate and a JSON description
    (firmware, robot geometry, and for the emulator where its simulated sensors are)."""

    version: int
    sensor_hz: int
    info: dict[str, Any] = field(default_factory=dict)

    def pack(self) -> bytes:
        """The HELLO_REPLY body."""
        return (
            _HELLO_REPLY.pack(self.version, self.sensor_hz)
            + json.dumps(self.info, separators=(",", ":")).encode()
        )

    @classmethod
    def unpack(cls, body: bytes) -> HelloReply:
        """A HELLO_REPLY body read back."""
        version, hz = _unpack(_HELLO_REPLY, body[: _HELLO_REPLY.size], "HELLO_REPLY")
        try:
            info = json.loads(body[_HELLO_REPLY.size :] or b"{}")
        except ValueError:
            raise PacketError("HELLO_REPLY description is not JSON") from None
        if not isinstance(info, dict):
            raise PacketError("HELLO_REPLY description is not a JSON object")
        return cls(version, hz, info)


@dataclass(frozen=True)
class Ack:
    """The MCU's answer to command ``seq``."""

    seq: int
    status: AckStatus

    def pack(self) -> bytes:
        """The ACK body."""
        return _ACK.pack(self.seq, int(self.status))

    @classmethod
    def unpack(cls, body: bytes) -> Ack:
        """An ACK body read back."""
        seq, status = _unpack(_ACK, body, "ACK")
        try:
            return cls(seq, AckStatus(status))
        except ValueError:
            raise PacketError(f"ACK status {status} is unknown") from None


@dataclass(frozen=True)
class Sensors:
    """One sample of everything the MCU measures."""

    t_ms: int  # the MCU's clock
    hall: tuple[int, int, int, int]  # edge counts per wheel FL, FR, RL, RR (signed, cumulative)
    ir_m: tuple[float, float, float, float]  # range of each IR sensor (IR_NAMES order)
    battery_v: tuple[float, float]  # main, logic
    current_a: tuple[float, float, float, float]  # motor currents FL, FR, RL, RR
    faults: Fault = Fault.NONE
    flags: Flag = Flag.NONE

    def pack(self) -> bytes:
        """The SENSORS body (ranges in mm, voltages in mV, currents in mA)."""
        return _SENSORS.pack(
            self.t_ms & 0xFFFFFFFF,
            *self.hall,
            *(min(0xFFFF, max(0, round(r * 1000))) for r in self.ir_m),
            *(min(0xFFFF, max(0, round(v * 1000))) for v in self.battery_v),
            *(_clamp_i16(round(a * 1000)) for a in self.current_a),
            int(self.faults),
            int(self.flags),
        )

    @classmethod
    def unpack(cls, body: bytes) -> Sensors:
        """A SENSORS body read back."""
        v = _unpack(_SENSORS, body, "SENSORS")
        return cls(
            v[0],
            (v[1], v[2], v[3], v[4]),
            (v[5] / 1000, v[6] / 1000, v[7] / 1000, v[8] / 1000),
            (v[9] / 1000, v[10] / 1000),
            (v[11] / 1000, v[12] / 1000, v[13] / 1000, v[14] / 1000),
            Fault(v[15]),
            Flag(v[16]),
        )


@dataclass(frozen=True)
class FaultReport:
    """A fault the MCU raised, with its words."""

    faults: Fault
    text: str

    def pack(self) -> bytes:
        """The FAULT body."""
        return _FAULT.pack(int(self.faults)) + self.text.encode()[:200]

    @classmethod
    def unpack(cls, body: bytes) -> FaultReport:
        """A FAULT body read back."""
        (bits,) = _unpack(_FAULT, body[: _FAULT.size], "FAULT")
        return cls(Fault(bits), body[_FAULT.size :].decode(errors="replace"))


def hello_body(version: int = PROTOCOL_VERSION) -> bytes:
    """The HELLO body: the host's protocol version."""
    return _HELLO.pack(version)


def hello_version(body: bytes) -> int:
    """The protocol version a HELLO body asks for."""
    return int(_unpack(_HELLO, body, "HELLO")[0])


def _unpack(layout: struct.Struct, body: bytes, name: str) -> tuple[Any, ...]:
    if len(body) != layout.size:
        raise PacketError(f"{name} body of {len(body)} bytes, expected {layout.size}")
    return layout.unpack(body)


def _clamp_i16(v: int) -> int:
    return max(-0x8000, min(0x7FFF, v))
