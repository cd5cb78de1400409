"""Which way the robot turns: its frame has x forward, y to its right and z into the
surface, so a turn to the right raises the yaw, the left wheels run faster than the right
ones, and the pose moves towards +y; the simulated robot, the MCU emulator and the agent's
Hall odometry agree."""

from __future__ import annotations

import numpy as np

from processing.poses import wheel_speeds, wheel_turn
from robot_link.agent.odometry import HallOdometry
from robot_link.emulator.firmware import Firmware
from robot_link.emulator.world import make_world
from robot_link.mcu.packets import Drive, PacketType
from robot_link.sim.robot import RobotSpec, SimRobot


def test_a_right_turn_runs_the_left_wheels_faster_and_raises_the_yaw() -> None:
    left, right = wheel_speeds(0.1, 0.5, 0.2)
    assert left > right  # turning right: the outer (left) wheels run faster
    assert np.isclose(wheel_turn(left, right, 0.2), 0.5)
    robot = SimRobot(RobotSpec(), np.random.default_rng(0))
    for _ in range(100):
        robot.step(0.05, 0.5, 0.01)  # a right turn for 1 s
    fl, fr, rl, rr = robot.wheel_speed
    assert fl > fr and rl > rr
    assert robot.pose[2] > 0.4 and robot.odom[2] > 0.4  # truth and odometry alike
    assert robot.pose[1] > 0  # towards its right, +y


def test_the_emulated_mcu_turns_its_world_the_way_its_wheels_drive() -> None:
    world = make_world(3)
    fw = Firmware(world)
    odometry = HallOdometry(world.spec.metres_per_tick, world.spec.track_m)
    odometry.update(fw.sensors().hall)
    yaw0 = float(world.robot.pose[2])
    for _ in range(50):  # left wheels ahead: a right turn
        fw.handle(PacketType.DRIVE, 1, Drive(0.08, 0.02, 0.2).pack())
        fw.tick(0.01)
        fw.tick(0.01)
        odometry.update(fw.sensors().hall)
    turned = float(world.robot.pose[2]) - yaw0
    assert turned > 0.1
    assert abs(float(odometry.pose[2]) - turned) < 0.2 * turned
