"""The simulated robot under teleoperation: it drives as the operator commands, streams live
video, captures frames and clouds every ``spacing`` (or on demand), and stops by itself when
commands stop arriving (the dead-man bound), when the link drops, or on e-stop.

Like :class:`robot_link.sim.inspection.InspectionSim` it talks to the station only through
:class:`robot_link.client.RobotLink`, exactly as the real on-board computer would.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from robot_link.client import RobotLink
from robot_link.protocol import DRIVE_HOLD_S, STOP_COMMANDS, Message, MessageType
from robot_link.sim.inspection import InspectionSim, SimConfig
from robot_link.sim.robot import IR_NAMES, edge_avoidance

FRONT, REAR = {0, 1}, {2, 3}  # IR sensor indices (IR_NAMES order)
# real time, 50 Hz control loop
TELEOP_SIM = SimConfig(time_scale=1.0, dt_s=0.02, telemetry_hz=10.0)


@dataclass(frozen=True)
class TeleopConfig:
    """Limits and rates of the teleoperated robot."""

    max_speed_mps: float = 0.15
    max_turn_radps: float = 0.8
    hold_s: float = DRIVE_HOLD_S  # dead-man: a drive command holds this long
    video_fps: float = 10.0
    video_quality: int = 70
    auto_capture: bool = True
    duration_s: float | None = None  # end the session after this long (None: on end_session)


@dataclass
class TeleopLog:
    """What the robot measured of its operator: for the teleop benchmark and tests."""

    # sent (operator clock) -> received
    command_latency_ms: list[float] = field(default_factory=list)
    # key pressed in the browser -> its drive command received
    key_latency_ms: list[float] = field(default_factory=list)
    deadman_stops_ms: list[float] = field(default_factory=list)  # last drive received -> standstill
    drive_commands: int = 0
    video_sent: int = 0
    refused: list[str] = field(default_factory=list)


class TeleopSim(InspectionSim):
    """A robot the operator drives."""

    def __init__(
        self,
        link: RobotLink,
        config: SimConfig = TELEOP_SIM,
        teleop: TeleopConfig = TeleopConfig(),
        **kwargs: Any,
    ) -> None:
        super().__init__(link, config, **kwargs)
        self.teleop = teleop
        self.v = self.w = 0.0
        self.last_drive = -np.inf  # monotonic time of the last drive command
        self.estopped = False
        self.blocked: list[int] = []  # IR sensors that block the commanded direction
        self.lift = {"front": False, "rear": False}
        self.auto_capture = teleop.auto_capture
        self.end_requested = False
        self.log = TeleopLog()
        # the video renders in its own thread
        self.video_rng = np.random.default_rng(config.seed + 99)
        link.on_link_change = self._on_link_change

    def _on_link_change(self, up: bool) -> None:
        if not up:  # the operator cannot see or stop the robot: stop now
            self.v = self.w = 0.0

    async def on_command(self, message: Message) -> None:
        """Act on an operator's command and acknowledge it (with why, when refused)."""
        cmd, args = message.meta.get("cmd"), message.meta.get("args", {})
        now_ms = time.time() * 1000
        if isinstance(args.get("sent_ms"), (int, float)):
            self.log.command_latency_ms.append(now_ms - float(args["sent_ms"]))
            if args.get("key_event"):
                self.log.key_latency_ms.append(self.log.command_latency_ms[-1])
        reason = self._apply(str(cmd), args)
        if reason:
            self.log.refused.append(f"{cmd}: {reason}")
        ack = {
            "cmd": cmd,
            "accepted": not reason,
            "reason": reason,
            "latency_ms": round(self.log.command_latency_ms[-1], 2)
            if "sent_ms" in args and self.log.command_latency_ms
            else None,
        }
        await self.link.notify(
            MessageType.COMMAND_ACK,
            {k: v for k, v in ack.items() if v is not None},
            seq=message.seq,
        )

    def _apply(self, cmd: str, args: dict[str, Any]) -> str:
        """Carry out one command; the reason it was refused, or ''."""
        if cmd == "drive":
            if self.estopped:
                return "emergency stop is engaged: resume first"
            try:
                v, w = float(args.get("linear_mps", 0.0)), float(args.get("angular_radps", 0.0))
            except (TypeError, ValueError):
                return "linear_mps and angular_radps must be numbers"
            if not (np.isfinite(v) and np.isfinite(w)):
                return "linear_mps and angular_radps must be finite"
            self.v = float(np.clip(v, -self.teleop.max_speed_mps, self.teleop.max_speed_mps))
            self.w = float(np.clip(w, -self.teleop.max_turn_radps, self.teleop.max_turn_radps))
            self.last_drive = time.monotonic()
            self.log.drive_commands += 1
        elif cmd in STOP_COMMANDS:
            self.v = self.w = 0.0
            self.estopped = self.estopped or cmd == "estop"
        elif cmd == "resume":
            self.estopped = False
        elif cmd == "capture":
            self.capture_requested = True
        elif cmd == "lift":
            axle = args.get("axle")
            if axle not in self.lift:
                return "axle must be front or rear"
            self.lift[axle] = bool(args.get("up", not self.lift[axle]))
        elif cmd == "auto_capture":
            self.auto_capture = bool(args.get("on", not self.auto_capture))
            spacing = args.get("spacing_m")
            if spacing is not None:
                try:
                    self.spacing_m = float(np.clip(float(spacing), 0.02, 1.0))
                except (TypeError, ValueError):
                    return "spacing_m must be a number"
        elif cmd == "end_session":
            self.end_requested = True
        else:
            return f"unknown command {cmd!r}"
        return ""

    def clock(self) -> float:
        """Real time: an operator drives this robot."""
        return time.time()

    def telemetry_meta(self) -> dict[str, Any]:
        """The inspection telemetry plus the drive state (speed, dead-man, lift, capture)."""
        meta = super().telemetry_meta()
        held = (time.monotonic() - self.last_drive) * 1000 if np.isfinite(self.last_drive) else None
        blocked = self.blocked if self.v else []
        if blocked:  # the robot holds still at the edge instead of Algorithm 1's back-off
            meta["edge_action"] = "block_forward" if self.v > 0 else "block_reverse"
        elif meta["edge_action"] != "none":
            meta["edge_action"] = "edge_near"  # the operator decides; nothing is blocked yet
        meta.update(
            {
                "mode": "teleop",
                "drive": {
                    "linear_mps": 0.0 if blocked else round(self.v, 4),
                    "commanded_linear_mps": round(self.v, 4),
                    "blocked_by": [IR_NAMES[i] for i in blocked],
                    "angular_radps": round(self.w, 4),
                    "last_command_ms": round(held, 1) if held is not None else None,
                    "hold_ms": self.teleop.hold_s * 1000,
                },
                "estop": self.estopped,
                "lift": dict(self.lift),
                "auto_capture": {"on": self.auto_capture, "spacing_m": round(self.spacing_m, 4)},
                "frames": self.result.frames_sent,
            }
        )
        return meta

    def _deadman(self) -> None:
        """Stop when the last drive command is older than the hold time."""
        if (self.v or self.w) and time.monotonic() - self.last_drive > self.teleop.hold_s:
            self.v = self.w = 0.0
            self.log.deadman_stops_ms.append((time.monotonic() - self.last_drive) * 1000)

    def _edge_guard(self) -> tuple[float, float]:
        """The commanded motion, without driving off the plate (the paper's Algorithm 1): no
        forward motion when a front IR sensor sees no surface, no reverse at the rear."""
        _, out = edge_avoidance(
            self.robot.ir_ranges(self.structure.on_plate),
            np.full(4, self.spec.ir_calibrated_m),
            self.cfg.ir_eps_m,
        )
        v = self.v
        side = FRONT if v > 0 else REAR if v < 0 else set()
        self.blocked = sorted(side & set(out))
        if self.blocked:
            self._edge_event(out)
            v = 0.0
        return v, self.w

    async def _video(self) -> None:
        """Stream live preview frames until the session ends."""
        period = 1.0 / self.teleop.video_fps
        while not self.end_requested:
            t0 = time.monotonic()
            # the exposure: latency is measured from here, rendering included
            captured = time.time()
            cam = self.camera.pose_in_world(self.robot.pose.copy())
            image = await asyncio.to_thread(self.camera.render, self.structure, cam, self.video_rng)
            ok, buf = cv2.imencode(
                ".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.teleop.video_quality]
            )
            meta = {"encoding": "jpeg", "width": image.shape[1], "height": image.shape[0]}
            if ok and await self.link.send_video(meta, buf.tobytes(), timestamp=captured):
                self.log.video_sent += 1
            await asyncio.sleep(max(0.0, period - (time.monotonic() - t0)))

    async def run(self) -> Any:
        """Drive as commanded until ``end_session`` (or the configured duration), then end the
        session and wait until the station acknowledged everything."""
        self._wall0 = time.monotonic()
        self._epoch0 = time.time()
        await self.link.send(
            MessageType.SESSION_START,
            {
                "structure": self.cfg.structure,
                "operator": self.cfg.operator,
                "location": self.cfg.location,
                "robot": "sim-teleop",
                "calibration": self.calibration(),
            },
        )
        video = asyncio.create_task(self._video())
        since = 0.0
        try:
            while not self.end_requested and (
                self.teleop.duration_s is None or self._sim_t < self.teleop.duration_s
            ):
                self._deadman()
                before = self.robot.odom.copy()
                await self.step(*self._edge_guard())
                since += float(np.hypot(*(self.robot.odom[:2] - before[:2])))
                if self.auto_capture and since >= self.spacing_m:
                    await self.capture()
                    since = 0.0
        finally:
            self.end_requested = True
            await asyncio.gather(video, return_exceptions=True)
        await self.link.send(
            MessageType.SESSION_END,
            {
                "reason": "operator ended the session",
                "frames": self.result.frames_sent,
                "clouds": self.result.clouds_sent,
            },
        )
        await self.link.flush(timeout_s=120)
        return self.result


@dataclass
class TeleopRobot:
    """A teleoperated simulated robot running in its own thread and event loop."""

    sim: TeleopSim
    session_id: str
    thread: Any

    def stop(self, timeout_s: float = 120) -> None:
        """End its session (sent and acknowledged) and wait for the thread."""
        self.sim.end_requested = True
        self.thread.join(timeout=timeout_s)


def start_teleop_robot(
    server_url: str,
    token: str,
    *,
    seed: int = 5,
    duration_s: float | None = None,
    video_fps: float = 10.0,
    timeout_s: float = 30,
) -> TeleopRobot:
    """Connect a teleoperated simulated robot to a ground station from a background thread."""
    import threading

    holder: dict[str, Any] = {}
    ready = threading.Event()

    def run() -> None:
        async def main() -> None:
            link = RobotLink(server_url, token)
            sim = TeleopSim(
                link,
                SimConfig(seed=seed, time_scale=1.0, dt_s=0.02, telemetry_hz=10.0),
                TeleopConfig(duration_s=duration_s, video_fps=video_fps),
            )
            holder.update(sim=sim, sid=str(link.session_id))
            await link.start()
            ready.set()
            try:
                await sim.run()
            finally:
                await link.close()

        asyncio.run(main())

    thread = threading.Thread(target=run, name="teleop-robot", daemon=True)
    thread.start()
    if not ready.wait(timeout_s):
        raise TimeoutError("the teleop robot did not start")
    return TeleopRobot(holder["sim"], holder["sid"], thread)
