"""The on-board agent: one asyncio process that connects the robot's MCU, camera and ToF to
the ground station, exactly as the simulator does (same client, spool, resend, dead-man).

It streams frames (every ``spacing`` of Hall distance, stamped with the odometry pose at
exposure), clouds, telemetry (with its own health) and a 10 fps preview, obeys the
dashboard's commands, and runs the coverage sweep when asked.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from processing.coverage import footprint
from robot_link.agent.camera import CameraError, CameraSource, camera_source
from robot_link.agent.config import RobotConfig
from robot_link.agent.control import Controller
from robot_link.agent.emulator_sensors import EmulatorSensors
from robot_link.agent.geometry import camera_geometry, robot_spec
from robot_link.agent.health import AgentHealth, telemetry_meta
from robot_link.agent.odometry import HallOdometry
from robot_link.agent.sweep import CoverageSweep, SweepParams, SweepStopped
from robot_link.agent.tof import TofError, TofSource, tof_source
from robot_link.client import RobotLink
from robot_link.clouds import encode_depth_png
from robot_link.mcu.link import McuLink
from robot_link.protocol import Message, MessageType
from robot_link.sim.sensors import tof_mount
from robot_link.spool import Spool

log = logging.getLogger(__name__)


class RobotAgent:
    """Runs one inspection session with the robot: until ``end_session`` or the end of the
    sweep, then ends the session and waits for every acknowledgement."""

    def __init__(self, config: RobotConfig, *, sweep: bool = False) -> None:
        self.cfg = config
        self.sweep_requested = sweep
        self.mcu = McuLink(
            config.mcu.device,
            baud=config.mcu.baud,
            silent_s=config.mcu.silent_ms / 1000,
            garbled_frames=config.mcu.garbled_frames,
        )
        self.sensors: EmulatorSensors | None = None
        self.camera: CameraSource | None = None
        self.tof: TofSource | None = None
        self.link: RobotLink | None = None
        self.health = AgentHealth()
        self.frames_sent = self.clouds_sent = 0
        self.end_requested = asyncio.Event()
        self.sweep: CoverageSweep | None = None
        self.sweep_error: str | None = None  # why the sweep could not go on
        self._since_capture = 0.0
        self._capture_lock = asyncio.Lock()
        self._capture_task: asyncio.Task[bool] | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self.auto_capture = True
        self.footprints: list[np.ndarray] = []  # what each frame shows, odometry frame
        self.capture_requested = False

    # start-up
    async def open_devices(self) -> None:
        """The MCU (handshake), the robot's geometry, the camera and the ToF; the first
        error (McuError, CameraError, TofError) stops the start."""
        reply = await self.mcu.open()
        info = reply.info
        self.spec = robot_spec(info.get("robot"), self.cfg)
        emulator = info.get("emulator") or {}
        if emulator.get("sensors"):
            self.sensors = EmulatorSensors(str(emulator["sensors"]))
        self.camera_geometry = camera_geometry(self.cfg, emulator)
        self.tof_mount = np.asarray(
            emulator.get("tof", {}).get("T_robot_tof")
            or self.cfg.tof.T_robot_tof
            or tof_mount().tolist(),
            float,
        )
        self.odometry = HallOdometry(self.spec.metres_per_tick, self.spec.track_m)
        self.control = Controller(self.cfg, self.mcu, self.odometry, self.spec)
        self.mcu.on_sensors = self.control.on_sensors
        self.mcu.on_fault = self.control.on_mcu_fault
        self.control.on_distance.append(self._distance)
        self.camera = camera_source(self.cfg.camera, self.sensors)
        await self.camera.open()
        self.tof = tof_source(self.cfg.tof, self.sensors, emulator)
        await self.tof.open()
        # a first frame proves the camera works before the session starts
        await self.camera.grab(exact=False)

    def spacing_m(self) -> float:
        """Capture spacing: the footprint along the heading times (1 - overlap)."""
        return self.camera_geometry.footprint_m[0] * (1 - self.cfg.camera.min_overlap)

    def sweep_params(self) -> SweepParams:
        """The sweep's lanes from the camera's footprint across the heading."""
        s = self.cfg.sweep
        return SweepParams(
            speed_mps=min(s.speed_mps, self.cfg.safety.max_speed_mps),
            turn_radps=min(s.turn_radps, self.cfg.safety.max_turn_radps),
            lane_width_m=self.camera_geometry.footprint_m[1] * (1 - s.lane_overlap),
            first_turn=-1 if s.first_turn == "left" else 1,
            # one Hall edge on each side turns the robot this much: no finer heading is seen
            heading_tolerance=self.spec.metres_per_tick / self.spec.track_m,
            sensor_reach_m=max(x for x, _ in self.spec.ir_corners_m),
        )

    def calibration(self) -> dict[str, Any]:
        """Sensor calibration for SESSION_START (as the simulator sends it)."""
        g = self.camera_geometry
        assert self.tof is not None
        return {
            "camera": {
                "width": g.width,
                "height": g.height,
                "px_per_m": g.px_per_m,
                "T_robot_camera": [g.mount_x_m, 0.0, 0.0],
            },
            "tof": {**self.tof.intrinsics, "T_robot_tof": self.tof_mount.tolist()},
            "capture_spacing_m": self.spacing_m(),
            "inclination_deg": self.cfg.safety.inclination_deg,
        }

    # the session
    async def run(self) -> dict[str, Any]:
        """Open everything, run the session, close everything; the summary."""
        await self.open_devices()
        st = self.cfg.station
        spool = Spool(Path(st.spool), max_bytes=int(st.spool_max_mb * 2**20)) if st.spool else None
        self.link = RobotLink(
            st.url,
            st.token,
            spool=spool,
            ca_file=st.ca_file,
            on_command=self.on_command,
            on_link_change=self.control.on_link,
        )
        await self.link.start()
        try:
            return await self._session()
        finally:
            self.control.stop()
            await self.mcu.close()
            await self.link.close()
            for dev in (self.camera, self.tof):
                if dev is not None:
                    await dev.close()
            if self.sensors is not None:
                await self.sensors.close()

    async def _session(self) -> dict[str, Any]:
        assert self.link is not None
        info = self.cfg.session
        await self._send(
            MessageType.SESSION_START,
            {
                "structure": info.structure,
                "operator": info.operator,
                "location": info.location,
                "robot": info.robot,
                "calibration": self.calibration(),
            },
        )
        tasks = [
            asyncio.create_task(self._telemetry()),
            asyncio.create_task(self._preview()),
        ]
        if self.sweep_requested:
            self.start_sweep()
        await self.end_requested.wait()
        self.control.set_sweep("stopped")
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if self._capture_task is not None:
            await asyncio.gather(self._capture_task, return_exceptions=True)
        await self._send(
            MessageType.SESSION_END,
            {
                "reason": "sweep completed"
                if self.sweep and self.sweep.progress.finished
                else "operator ended the session",
                "frames": self.frames_sent,
                "clouds": self.clouds_sent,
            },
        )
        await self.link.flush(timeout_s=600)
        return self.summary()

    def summary(self) -> dict[str, Any]:
        """The JSON line ``steelscan robot`` prints at the end."""
        assert self.link is not None
        out: dict[str, Any] = {
            "session_id": str(self.link.session_id),
            "frames_sent": self.frames_sent,
            "clouds_sent": self.clouds_sent,
        }
        if self.sweep is not None:
            out["lanes"] = self.sweep.progress.lanes_done
            out["sweep_finished"] = self.sweep.progress.finished
            out["sweep_phase"] = self.sweep.progress.phase
        if self.sweep_error:
            out["sweep_error"] = self.sweep_error
        return out

    def start_sweep(self) -> None:
        """Start the coverage sweep (or resume a paused one)."""
        if self.sweep is not None and not self.sweep.progress.finished:
            self.control.set_sweep("running")
            return
        self.sweep = CoverageSweep(_SweepPilot(self), self.sweep_params())
        self.control.set_sweep("running")
        self._background(self._run_sweep(self.sweep))

    async def _run_sweep(self, sweep: CoverageSweep) -> None:
        try:
            await sweep.run()
        except SweepStopped as exc:
            sweep.progress.phase = f"stopped: {exc or 'by the operator'}"
            log.info("sweep %s", sweep.progress.phase)
            if str(exc):  # the robot cannot go on
                self.sweep_error = str(exc)
                if self.sweep_requested:
                    self.end_requested.set()
            return
        self.control.set_sweep("done")
        if self.sweep_requested:
            self.end_requested.set()

    def _background(self, work: Coroutine[Any, Any, None]) -> None:
        """Run ``work`` as a task the agent holds until it ends (the loop keeps only weak
        references to tasks)."""
        task = asyncio.create_task(work)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # frames and clouds
    def request_capture(self) -> None:
        """Take a frame as soon as no other is being taken."""
        self.capture_requested = True
        self._distance(0.0)

    def _distance(self, moved: float) -> None:
        self._since_capture += moved
        due = self.auto_capture and self._since_capture >= self.spacing_m()
        if (due or self.capture_requested) and (
            self._capture_task is None or self._capture_task.done()
        ):
            self.capture_requested = False
            self._capture_task = asyncio.create_task(self.capture())

    async def capture(self) -> bool:
        """Take an inspection frame (and a cloud every ``every_frames``) and send them with
        the odometry pose at the exposure; False when the camera failed."""
        assert self.camera is not None and self.tof is not None
        async with self._capture_lock:
            self._since_capture = 0.0
            pose = self.odometry.as_meta()
            stamp = time.time()
            try:
                grab = await self.camera.grab(exact=True)
            except CameraError as exc:
                self.health.camera_error = str(exc)
                self._background(self._reopen_camera())
                return False
            self.health.camera_error = None
            self.health.count("frames")
            h, w = grab.image.shape[:2]
            ok, jpeg = cv2.imencode(
                ".jpg", grab.image, [cv2.IMWRITE_JPEG_QUALITY, self.cfg.camera.jpeg_quality]
            )
            await self._send(
                MessageType.FRAME,
                {"encoding": "jpeg", "width": w, "height": h, "pose": pose},
                jpeg.tobytes(),
                timestamp=stamp,
            )
            self.frames_sent += 1
            self.footprints.append(self._footprint(pose))
            if self.frames_sent % self.cfg.tof.every_frames == 0:
                await self._cloud(pose, stamp)
            return True

    def _footprint(self, pose: dict[str, float]) -> np.ndarray:
        g = self.camera_geometry
        x, y, yaw = pose["x"], pose["y"], pose["yaw"]
        cam = np.array([x + g.mount_x_m * np.cos(yaw), y + g.mount_x_m * np.sin(yaw), yaw])
        return footprint(cam, g.px_per_m, (g.width, g.height))

    async def capture_until_done(self) -> None:
        """Capture, holding still while the camera reconnects (the sweep leaves no hole)."""
        while not await self.capture():
            await asyncio.sleep(1.0)

    async def _cloud(self, pose: dict[str, float], stamp: float) -> None:
        assert self.tof is not None
        try:
            depth = await self.tof.grab()
        except TofError as exc:
            self.health.tof_error = str(exc)
            return
        self.health.tof_error = None
        self.health.count("clouds")
        await self._send(
            MessageType.CLOUD,
            {"encoding": "png16_depth_mm", **self.tof.intrinsics, "pose": pose},
            encode_depth_png(depth.depth_m),
            timestamp=stamp,
        )
        self.clouds_sent += 1

    async def _reopen_camera(self) -> None:
        assert self.camera is not None
        with contextlib.suppress(CameraError):
            await self.camera.close()
            await asyncio.sleep(1.0)
            await self.camera.open()
            self.health.camera_error = None

    async def _preview(self) -> None:
        """The live preview at ``preview_fps``."""
        assert self.camera is not None and self.link is not None
        period = 1.0 / self.cfg.camera.preview_fps
        while True:
            t0 = time.monotonic()
            if not self._capture_lock.locked():
                with contextlib.suppress(CameraError):
                    grab = await self.camera.grab(exact=False)
                    small = cv2.resize(
                        grab.image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA
                    )
                    ok, jpeg = cv2.imencode(
                        ".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, self.cfg.camera.preview_quality]
                    )
                    meta = {"encoding": "jpeg", "width": small.shape[1], "height": small.shape[0]}
                    if ok and await self.link.send_video(
                        meta, jpeg.tobytes(), timestamp=time.time()
                    ):
                        self.health.count("preview")
            await asyncio.sleep(max(0.0, period - (time.monotonic() - t0)))

    async def _telemetry(self) -> None:
        period = 1.0 / self.cfg.telemetry_hz
        while True:
            await self._send(MessageType.TELEMETRY, telemetry_meta(self))
            await asyncio.sleep(period)

    async def _send(
        self,
        mtype: MessageType,
        meta: dict[str, Any],
        payload: bytes = b"",
        *,
        timestamp: float | None = None,
    ) -> int:
        assert self.link is not None
        return await self.link.send(mtype, meta, payload, timestamp=timestamp or time.time())

    # the operator
    async def on_command(self, message: Message) -> None:
        """Carry out an operator's command and acknowledge it (with why, when refused)."""
        from robot_link.agent.commands import apply_command

        cmd, args = str(message.meta.get("cmd")), message.meta.get("args", {}) or {}
        reason = apply_command(self, cmd, args)
        assert self.link is not None
        ack = {"cmd": cmd, "accepted": not reason}
        if reason:
            ack["reason"] = reason
        await self.link.notify(MessageType.COMMAND_ACK, ack, seq=message.seq)


class _SweepPilot:
    """The controller as the sweep's pilot, capturing through the agent."""

    def __init__(self, agent: RobotAgent) -> None:
        self.agent = agent
        self.control = agent.control

    @property
    def pose(self) -> np.ndarray:
        return self.control.pose

    def ir_out(self) -> list[int]:
        return self.control.ir_out()

    def set_heading(self, heading: float) -> None:
        self.control.set_heading(heading)

    async def step(self, v: float, w: float) -> None:
        await self.control.step(v, w)

    async def capture(self) -> None:
        await self.agent.capture_until_done()

    def frame_footprints(self) -> list[np.ndarray]:
        return list(self.agent.footprints)
