"""The MCU's own safety layer, in the emulator's firmware: the dead-man, the e-stop latch,
the edge guard of Algorithm 1 (the wheels stop before leaving the plate, whatever the host
asks), and the contract's header."""

from __future__ import annotations

import math

import numpy as np

from robot_link.emulator.firmware import Firmware
from robot_link.emulator.world import make_world
from robot_link.mcu.packets import Ack, AckStatus, Drive, Fault, PacketType

TICK = 0.01


def drive(fw: Firmware, v: float, hold_s: float = 0.2) -> AckStatus:
    _, body = fw.handle(PacketType.DRIVE, 1, Drive(v, v, hold_s).pack())
    return Ack.unpack(body).status


def test_the_header_states_plate_robot_and_footprint() -> None:
    world = make_world(9)
    h = world.header()
    assert h["plate"]["width"] > 0.6 and h["plate"]["height"] > 0.5
    assert h["robot"]["length"] > 0 and h["robot"]["width"] > 0
    fp = h["camera_footprint"]
    # the footprint reaches past the IR sensors, so the band along each edge can be seen
    ir_ahead = max(x for x, _ in world.spec.ir_corners_m)
    assert fp["height"] / 2 > ir_ahead and fp["width"] / 2 > ir_ahead


def test_the_deadman_stops_the_wheels() -> None:
    fw = Firmware(make_world(1))
    assert drive(fw, 0.1, hold_s=3.0) is AckStatus.OK
    for _ in range(15):
        fw.tick(TICK)
    assert fw.wheels[0] > 0
    for _ in range(40):
        fw.tick(TICK)
    assert fw.wheels == (0.0, 0.0)


def test_the_estop_latches_until_reset() -> None:
    fw = Firmware(make_world(1))
    fw.handle(PacketType.ESTOP, 2, b"")
    assert drive(fw, 0.1) is AckStatus.ESTOP_LATCHED
    fw.tick(TICK)
    assert fw.faults & Fault.ESTOP
    fw.handle(PacketType.RESET_ESTOP, 3, b"")
    assert drive(fw, 0.1) is AckStatus.OK


def test_the_wheels_stop_at_an_edge_whatever_the_host_asks() -> None:
    world = make_world(2, (0.9, 0.7))
    world.robot.pose[:] = (0.6, 0.35, 0.0)  # facing the edge at x = 0.9
    fw = Firmware(world)
    out_at = None
    for i in range(600):
        if i % 2 == 0:
            drive(fw, 0.15)  # a host that keeps driving ahead
        fw.tick(TICK)
        if out_at is None and fw.ir_out():
            out_at = fw.t_s
        if out_at is not None and fw.wheels == (0.0, 0.0):
            break
    assert out_at is not None and world.wheels_on_plate()
    assert fw.t_s - out_at <= 0.1  # stopped within 100 ms of the sensor seeing no surface
    x = world.robot.pose[0]
    for _ in range(100):
        drive(fw, 0.15)
        fw.tick(TICK)
    assert world.robot.pose[0] == x  # no further forward


def test_turning_in_place_stays_allowed_at_an_edge() -> None:
    world = make_world(2, (0.9, 0.7))
    world.robot.pose[:] = (0.9 - 0.117, 0.35, 0.0)
    fw = Firmware(world)
    assert fw.ir_out()
    for _ in range(100):
        fw.handle(PacketType.DRIVE, 1, Drive(-0.05, 0.05, 0.2).pack())
        fw.tick(TICK)
    assert abs(world.robot.pose[2]) > math.radians(10)
    assert world.wheels_on_plate()
    assert np.hypot(*(world.robot.pose[:2] - (0.783, 0.35))) < 0.01
