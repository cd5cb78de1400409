"""A simulated inspection: the robot sweeps the plate in lanes, captures, and streams it all.

The robot connects through :class:`robot_link.client.RobotLink` exactly as the real
on-board computer would.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from processing.poses import compose_se2, relative_se2
from robot_link.client import RobotLink
from robot_link.clouds import encode_depth_png
from robot_link.protocol import STOP_COMMANDS, Message, MessageType
from robot_link.sim.robot import (
    IR_NAMES,
    EdgeAction,
    RobotSpec,
    SimRobot,
    adhesion_margin,
    edge_avoidance,
)
from robot_link.sim.sensors import DownwardCamera, TofCamera
from robot_link.sim.structure import SteelStructure, make_structure

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimConfig:
    """How the simulated inspection runs."""

    seed: int = 7
    lanes: int = 5
    first_lane_y_m: float = 0.15
    start_x_m: float = 0.2
    min_overlap: float = 0.30
    speed_mps: float = 0.10
    turn_rate: float = 0.6
    dt_s: float = 0.05
    time_scale: float = 20.0  # simulated seconds per wall second; 0 = as fast as possible
    telemetry_hz: float = 4.0
    structure: str = "Simulated plate girder G3, span 2"
    operator: str = "demo"
    location: str = "Steelscan test yard (simulated)"
    inclination_deg: float = 90.0
    ir_eps_m: float = 0.02
    flush_timeout_s: float = 120.0  # wait this long at the end for every ACK
    # where the robot truly starts relative to where it believes (x, y in metres, yaw in
    # radians, in its start pose's frame): a robot set down off the structure's datum
    start_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class SimResult:
    """What the simulated robot sent and the ground truth to score the station against."""

    session_id: str
    frames_sent: int = 0
    clouds_sent: int = 0
    telemetry_sent: int = 0
    edge_events: int = 0
    frame_poses_true: list[list[float]] = field(default_factory=list)  # camera x, y, yaw
    # seq -> T_world_tof
    cloud_poses_true: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    # what odometry said
    cloud_poses_odom: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    structure: SteelStructure | None = None
    frame_size: tuple[int, int] = (640, 480)  # (w, h) of the camera frames

    def summary(self) -> dict[str, Any]:
        """The JSON line ``steelscan sim`` prints."""
        return {
            "session_id": self.session_id,
            "frames_sent": self.frames_sent,
            "clouds_sent": self.clouds_sent,
            "telemetry_sent": self.telemetry_sent,
            "edge_events": self.edge_events,
        }


class InspectionSim:
    """Drives the robot over its route, capturing frames and clouds every ``spacing``."""

    def __init__(
        self,
        link: RobotLink,
        config: SimConfig = SimConfig(),
        *,
        structure: SteelStructure | None = None,
        progress: Callable[[float, str], None] | None = None,
    ) -> None:
        self.link = link
        self.cfg = config
        self.rng = np.random.default_rng(config.seed + 1)
        self.structure = structure or make_structure(config.seed)
        self.spec = RobotSpec()
        self.camera = DownwardCamera()
        self.tof = TofCamera(self.structure)
        start = np.array([config.start_x_m, config.first_lane_y_m, 0.0])
        true_start = compose_se2(start, np.asarray(config.start_offset, float))
        self.robot = SimRobot(self.spec, self.rng, pose=true_start, odom=start.copy())
        self.spacing_m = self.camera.capture_spacing_m(config.min_overlap)
        self.lane_spacing_m = float(
            np.floor(self.camera.footprint_m[1] * (1 - config.min_overlap) * 100) / 100
        )
        self.result = SimResult(
            session_id=str(link.session_id),
            structure=self.structure,
            frame_size=(self.camera.width, self.camera.height),
        )
        self.progress = progress
        self.paused = False
        self.capture_requested = False
        self._sim_t = 0.0
        self._wall0 = 0.0
        self._epoch0 = time.time()  # the robot's clock when the simulation started
        self._next_telemetry = 0.0
        self._last_edge: list[int] = []
        link.on_command = self.on_command

    def datum(self) -> NDArray[np.float64]:
        """The session's world frame (the robot's odometry frame) on the structure: the true
        pose of the world's origin, (x, y, yaw)."""
        start = np.array([self.cfg.start_x_m, self.cfg.first_lane_y_m, 0.0])
        true_start = compose_se2(start, np.asarray(self.cfg.start_offset, float))
        return compose_se2(true_start, relative_se2(start, np.zeros(3)))

    def calibration(self) -> dict[str, Any]:
        """Sensor calibration sent with SESSION_START (T_robot_camera, T_robot_tof, ...)."""
        return {
            "camera": {
                "width": self.camera.width,
                "height": self.camera.height,
                "px_per_m": 1.0 / self.camera.m_per_px,
                "T_robot_camera": [self.camera.mount_x_m, 0.0, 0.0],
            },
            "tof": {**self.tof.intrinsics(), "T_robot_tof": self.tof.T_robot_tof.tolist()},
            "capture_spacing_m": self.spacing_m,
            "inclination_deg": self.cfg.inclination_deg,
        }

    async def on_command(self, message: Message) -> None:
        """Obey the operator: stop/estop pause the route, resume continues, capture shoots."""
        cmd = message.meta.get("cmd")
        if cmd in STOP_COMMANDS:
            self.paused = True
        elif cmd == "resume":
            self.paused = False
        elif cmd == "capture":
            self.capture_requested = True
        await self.link.notify(
            MessageType.COMMAND_ACK,
            {"cmd": cmd, "accepted": cmd in ("stop", "estop", "resume", "capture")},
            seq=message.seq,
        )

    async def run(self) -> SimResult:
        """Run the whole route and wait until the station acknowledged everything."""
        self._wall0 = time.monotonic()
        self._epoch0 = time.time()
        await self._send(
            MessageType.SESSION_START,
            {
                "structure": self.cfg.structure,
                "operator": self.cfg.operator,
                "location": self.cfg.location,
                "robot": "sim",
                "calibration": self.calibration(),
            },
        )
        heading = 0.0
        for lane in range(self.cfg.lanes):
            lane_y = self.cfg.first_lane_y_m + lane * self.lane_spacing_m
            await self.capture()
            await self.drive_lane(lane_y, heading)
            await self.capture()
            self._report(lane + 1)
            if lane == self.cfg.lanes - 1:
                break
            await self.drive(-0.05)
            turn = np.pi / 2 if heading == 0.0 else -np.pi / 2
            await self.rotate(turn)
            await self.drive(lane_y + self.lane_spacing_m - float(self.robot.odom[1]))
            await self.rotate(turn)
            heading = np.pi if heading == 0.0 else 0.0
        await self._send(
            MessageType.SESSION_END,
            {
                "reason": "route completed",
                "frames": self.result.frames_sent,
                "clouds": self.result.clouds_sent,
            },
        )
        await self.link.flush(timeout_s=self.cfg.flush_timeout_s)
        return self.result

    def _report(self, lanes_done: int) -> None:
        if self.progress is not None:
            self.progress(
                lanes_done / self.cfg.lanes,
                f"lane {lanes_done}/{self.cfg.lanes}, {self.result.frames_sent} frames",
            )

    async def drive_lane(self, lane_y: float, heading: float) -> None:
        """Follow the lane (odometry line following), capturing every spacing, to the edge."""
        since = 0.0
        while True:
            action, out = edge_avoidance(
                self.robot.ir_ranges(self.structure.on_plate),
                np.full(4, self.spec.ir_calibrated_m),
                self.cfg.ir_eps_m,
            )
            if action is EdgeAction.stop_and_wait or (out and set(out) <= {0, 1}):
                # the front sensors reached the plate's end: stop; the route planner turns
                self._edge_event(out)
                return
            if action is not EdgeAction.none:
                self._edge_event(out)
                await self.drive(-0.05)
                await self.rotate(-0.1 if action is EdgeAction.back_off_turn_left else 0.1)
                continue
            before = self.robot.odom.copy()
            yaw_err = (heading - before[2] + np.pi) % (2 * np.pi) - np.pi
            w = 3.0 * yaw_err + 8.0 * (lane_y - before[1]) * np.cos(heading)
            await self.step(self.cfg.speed_mps, float(np.clip(w, -0.3, 0.3)))
            since += float(np.hypot(*(self.robot.odom[:2] - before[:2])))
            if since >= self.spacing_m - 1e-9:
                await self.capture()
                since = 0.0

    def _edge_event(self, out: list[int]) -> None:
        if out != self._last_edge:
            self.result.edge_events += 1
        self._last_edge = out

    async def drive(self, distance_m: float) -> None:
        """Drive straight by ``distance_m`` as measured by odometry (negative: reverse)."""
        start = self.robot.odom.copy()
        v = self.cfg.speed_mps * np.sign(distance_m)
        while np.hypot(*(self.robot.odom[:2] - start[:2])) < abs(distance_m):
            await self.step(v, 0.0)

    async def rotate(self, angle: float) -> None:
        """Turn in place by ``angle`` radians as measured by odometry (to its resolution)."""
        target = self.robot.odom[2] + angle
        resolution = self.spec.metres_per_tick / self.spec.track_m
        for _ in range(int(abs(angle) / (self.cfg.turn_rate * self.cfg.dt_s)) + 200):
            err = (target - self.robot.odom[2] + np.pi) % (2 * np.pi) - np.pi
            if abs(err) < resolution:
                return
            w = float(np.clip(err / self.cfg.dt_s, -self.cfg.turn_rate, self.cfg.turn_rate))
            await self.step(
                0.0,
                w
                if abs(w) * self.cfg.dt_s >= resolution
                else np.sign(err) * resolution / self.cfg.dt_s,
            )

    async def step(self, v: float, w: float) -> None:
        """Advance the simulation by one time step, pacing to wall time and sending telemetry."""
        while self.paused:  # the robot's clock runs on while it waits
            await self.send_telemetry()
            await asyncio.sleep(0.1)
            self._sim_t += 0.1 * (self.cfg.time_scale or 1.0)
        if self.capture_requested:
            self.capture_requested = False
            await self.capture()
        self.robot.step(v, w, self.cfg.dt_s)
        self.robot.pose[2] += self.rng.normal(0, 0.0004) if v else 0.0
        self._sim_t += self.cfg.dt_s
        if self._sim_t >= self._next_telemetry:
            await self.send_telemetry()
            self._next_telemetry = self._sim_t + 1.0 / self.cfg.telemetry_hz
        if self.cfg.time_scale > 0:
            ahead = self._sim_t / self.cfg.time_scale - (time.monotonic() - self._wall0)
            await asyncio.sleep(max(0.0, ahead))
        else:
            await asyncio.sleep(0)

    def clock(self) -> float:
        """The robot's clock (s since the epoch): simulated time, which runs ``time_scale``
        times faster than the wall's, so a session's timestamps span the inspection's time."""
        # whole nanoseconds, as time.time() gives them (and MCAP stores them)
        return round((self._epoch0 + self._sim_t) * 1e9) / 1e9

    async def _send(self, mtype: MessageType, meta: dict[str, Any], payload: bytes = b"") -> int:
        return await self.link.send(mtype, meta, payload, timestamp=self.clock())

    async def send_telemetry(self) -> None:
        """Send one telemetry sample."""
        await self._send(MessageType.TELEMETRY, self.telemetry_meta())
        self.result.telemetry_sent += 1

    def telemetry_meta(self) -> dict[str, Any]:
        """One telemetry sample: odometry, Hall wheel speeds/distances, IR, batteries, adhesion."""
        r = self.robot
        ranges = r.ir_ranges(self.structure.on_plate)
        action, out = edge_avoidance(
            ranges, np.full(4, self.spec.ir_calibrated_m), self.cfg.ir_eps_m
        )
        meta = {
            "pose": {"x": float(r.odom[0]), "y": float(r.odom[1]), "yaw": float(r.odom[2])},
            "wheel_speed_mps": [round(float(v), 4) for v in r.wheel_speed],
            "wheel_distance_m": [
                round(float(t * self.spec.metres_per_tick), 4) for t in r.wheel_ticks
            ],
            "ir_range_m": [round(float(v), 4) for v in ranges],
            "ir_no_surface": [IR_NAMES[i] for i in out],
            "edge_action": action.value,
            "battery_v": {
                "main": round(r.batteries.main_v, 3),
                "logic": round(r.batteries.logic_v, 3),
            },
            "inclination_deg": self.cfg.inclination_deg,
            "adhesion_margin": round(adhesion_margin(self.spec, self.cfg.inclination_deg), 3),
            "distance_m": round(r.distance_m, 4),
            "paused": self.paused,
            "link": {
                "pending": self.link.pending,
                "resent": self.link.stats.resent,
                "ack_latency_ms": round(self.link.stats.last_ack_latency_s * 1000, 2),
                "reconnects": self.link.stats.reconnects,
                "video_dropped": self.link.stats.video_dropped,
            },
        }
        return meta

    async def capture(self) -> None:
        """Stop, take a camera frame and a ToF cloud, and send both with the odometry pose."""
        r = self.robot
        odom_pose = {"x": float(r.odom[0]), "y": float(r.odom[1]), "yaw": float(r.odom[2])}
        cam_true = self.camera.pose_in_world(r.pose)
        # rendered off the event loop: the link keeps reading commands meanwhile
        image = await asyncio.to_thread(
            partial(self.camera.render, exact=True), self.structure, cam_true, self.rng
        )
        await self._send(
            MessageType.FRAME,
            {
                "encoding": "jpeg",
                "width": self.camera.width,
                "height": self.camera.height,
                "pose": odom_pose,
            },
            self.camera.encode(image),
        )
        self.result.frames_sent += 1
        self.result.frame_poses_true.append([float(v) for v in cam_true])
        T_true = self.tof.T_world_tof(r.pose)
        depth = await asyncio.to_thread(self.tof.render, T_true, self.rng)
        seq = await self._send(
            MessageType.CLOUD,
            {"encoding": "png16_depth_mm", **self.tof.intrinsics(), "pose": odom_pose},
            encode_depth_png(depth),
        )
        self.result.clouds_sent += 1
        self.result.cloud_poses_true[seq] = T_true
        self.result.cloud_poses_odom[seq] = self.tof.T_world_tof(r.odom)
