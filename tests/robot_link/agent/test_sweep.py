"""The coverage sweep's route on the emulator's firmware and physics stepped as fast as they
compute (no pty, no clock): on plates of seeds the sweep was not developed on it covers
≥ 99 % of the plate, the band along every edge included, and no wheel leaves the plate;
frames the camera lost are made up by visiting the holes."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from numpy.typing import NDArray

from processing.coverage import footprint
from processing.poses import wheel_speeds
from robot_link.agent.odometry import HallOdometry
from robot_link.agent.sweep import CoverageSweep, SweepParams
from robot_link.emulator.coverage import footprint_coverage
from robot_link.emulator.firmware import Firmware
from robot_link.emulator.world import World, make_world
from robot_link.mcu.packets import Drive, PacketType


class FirmwarePilot:
    """The sweep's pilot on the firmware directly: 20 ms control steps of two 10 ms ticks."""

    def __init__(self, world: World, lose_frames: range = range(0)) -> None:
        self.world = world
        self.fw = Firmware(world)
        spec = world.spec
        self.odometry = HallOdometry(spec.metres_per_tick, spec.track_m)
        self.odometry.update(self.fw.sensors().hall)
        self.states: list[dict[str, float]] = []
        self.footprints: list[NDArray[np.float64]] = []
        self.true_frames: list[dict[str, float]] = []
        self.lose_frames = lose_frames
        self.shots = 0
        self.since = 0.0
        self.spacing = world.camera.capture_spacing_m(0.3)

    @property
    def pose(self) -> NDArray[np.float64]:
        return self.odometry.pose

    def ir_out(self) -> list[int]:
        return self.fw.ir_out()

    def set_heading(self, heading: float) -> None:
        self.odometry.set_heading(heading)

    async def step(self, v: float, w: float) -> None:
        left, right = wheel_speeds(v, w, self.world.spec.track_m)
        self.fw.handle(PacketType.DRIVE, 1, Drive(left, right, 0.2).pack())
        for _ in range(2):
            self.fw.tick(0.01)
        self.since += self.odometry.update(self.fw.sensors().hall)
        if self.since >= self.spacing:  # auto-capture, as the agent does
            await self.capture()
        x, y, heading = (float(c) for c in self.world.robot.pose)
        self.states.append(
            {"x": x, "y": y, "heading": heading, "on_plate": self.world.wheels_on_plate()}
        )
        assert len(self.states) < 200_000, "the sweep does not end"

    async def capture(self) -> None:
        self.shots += 1
        self.since = 0.0
        if self.shots in self.lose_frames:
            return
        cam = self.world.camera
        self.footprints.append(
            footprint(self.pose.copy(), 1 / cam.m_per_px, (cam.width, cam.height))
        )
        self.true_frames.append(self.states[-1] if self.states else self._true())

    def _true(self) -> dict[str, float]:
        x, y, heading = (float(c) for c in self.world.robot.pose)
        return {"x": x, "y": y, "heading": heading}

    def frame_footprints(self) -> list[NDArray[np.float64]]:
        return list(self.footprints)


def params(world: World) -> SweepParams:
    across = world.camera.footprint_m[1]
    spec = world.spec
    return SweepParams(
        lane_width_m=across * 0.7,
        heading_tolerance=spec.metres_per_tick / spec.track_m,
        sensor_reach_m=max(x for x, _ in spec.ir_corners_m),
    )


@pytest.mark.parametrize("seed", [8101, 8202, 8303, 8404, 8505])
def test_the_sweep_covers_every_plate_and_keeps_its_wheels_on(seed: int) -> None:
    world = make_world(seed)
    pilot = FirmwarePilot(world)
    progress = asyncio.run(CoverageSweep(pilot, params(world)).run())
    assert progress.finished and progress.lanes_done >= 2
    assert all(s["on_plate"] for s in pilot.states)
    coverage, _ = footprint_coverage(world.header(), pilot.states)
    assert coverage >= 0.99, (seed, world.header()["plate"], coverage)
    # the frames alone cover it too (what the mosaic is made of)
    frames, _ = footprint_coverage(world.header(), pilot.true_frames)
    assert frames >= 0.99


def test_frames_the_camera_lost_are_made_up_by_visiting_the_holes() -> None:
    world = make_world(8606, (1.2, 0.8))
    pilot = FirmwarePilot(world, lose_frames=range(9, 12))
    progress = asyncio.run(CoverageSweep(pilot, params(world)).run())
    assert progress.holes_visited >= 1
    frames, _ = footprint_coverage(world.header(), pilot.true_frames)
    assert frames >= 0.99
    assert all(s["on_plate"] for s in pilot.states)
    assert not math.isnan(frames)
