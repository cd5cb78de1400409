"""The protocol's packets keep their values through the wire (to the units' resolution) and
refuse bodies of the wrong size."""

from __future__ import annotations

import pytest

from robot_link.mcu.packets import (
    Ack,
    AckStatus,
    Drive,
    Fault,
    FaultReport,
    Flag,
    HelloReply,
    Lift,
    PacketError,
    Sensors,
    hello_body,
    hello_version,
)


def test_packets_round_trip() -> None:
    s = Sensors(
        1234,
        (10, -20, 30, -40),
        (0.031, 0.5, 0.029, 0.03),
        (12.31, 8.02),
        (0.4, -0.4, 0.1, 0.0),
        Fault.EDGE | Fault.DEADMAN,
        Flag.MOVING | Flag.BLOCKED_FORWARD,
    )
    assert Sensors.unpack(s.pack()) == s
    assert Drive.unpack(Drive(0.123, -0.05, 0.2).pack()) == Drive(0.123, -0.05, 0.2)
    assert Lift.unpack(Lift("rear", True).pack()) == Lift("rear", True)
    assert Ack.unpack(Ack(7, AckStatus.ESTOP_LATCHED).pack()) == Ack(7, AckStatus.ESTOP_LATCHED)
    reply = HelloReply(1, 50, {"firmware": "x", "robot": {"track_m": 0.16}})
    assert HelloReply.unpack(reply.pack()) == reply
    assert FaultReport.unpack(FaultReport(Fault.LOW_BATTERY, "10.6 V").pack()).text == "10.6 V"
    assert hello_version(hello_body()) == 1


def test_drive_speeds_saturate_instead_of_wrapping() -> None:
    assert Drive.unpack(Drive(40.0, -40.0, 99.0).pack()) == Drive(32.767, -32.768, 65.535)


@pytest.mark.parametrize(
    "unpack,body",
    [
        (Sensors.unpack, b"\x00" * 10),
        (Drive.unpack, b"\x00" * 5),
        (Ack.unpack, b"\x01\x63"),
        (Lift.unpack, b"\x07\x01"),
        (HelloReply.unpack, b"\x01\x32\x00not json"),
    ],
)
def test_malformed_bodies_are_refused(unpack, body) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(PacketError):
        unpack(body)
