"""The drive control loop: the operator's commands or the sweep's, through the safety layer,
to the MCU's wheels. The MCU's sensor stream (50 Hz) clocks it; an operator's drive command
and anything that must stop the robot (link loss, e-stop, a silent MCU) act at once.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from processing.poses import wheel_speeds
from robot_link.agent.config import RobotConfig
from robot_link.agent.odometry import HallOdometry
from robot_link.agent.safety import SafetyInputs, Verdict, allowed_motion
from robot_link.agent.sweep import SweepStopped
from robot_link.mcu.link import McuError, McuLink
from robot_link.mcu.packets import Fault, Flag, PacketType, Sensors
from robot_link.sim.robot import RobotSpec, adhesion_margin

SWEEP_STATES = ("idle", "running", "paused", "stopped", "done")


@dataclass
class DriveLog:
    """What the controller measured: for the benchmarks and telemetry."""

    # operator's send time -> DRIVE written to the MCU (ms), per drive command
    command_to_mcu_ms: list[float] = field(default_factory=list)
    # a key pressed in the browser (the key event's time) -> its DRIVE written to the MCU (ms)
    key_to_mcu_ms: list[float] = field(default_factory=list)
    drives_sent: int = 0
    stops_sent: int = 0
    deadman_stops: int = 0


class Controller:
    """Chooses the motion, checks it and sends it to the MCU."""

    def __init__(self, config: RobotConfig, mcu: McuLink, odometry: HallOdometry, spec: RobotSpec):
        self.cfg = config
        self.mcu = mcu
        self.odometry = odometry
        self.spec = spec
        self.safety = SafetyInputs()
        self.mode = "idle"  # idle | teleop | sweep
        self.sweep_state = "idle"
        self.operator = (0.0, 0.0)
        self.operator_t = -np.inf  # monotonic time of the operator's last drive command
        self.auto = (0.0, 0.0)
        self.verdict = Verdict(0.0, 0.0)
        self.lifts = {"front": False, "rear": False}
        self.latest: Sensors | None = None
        self.log = DriveLog()
        self._moving = False
        self._sample = asyncio.Event()
        # called with the distance moved at each sample (auto-capture)
        self.on_distance: list[Callable[[float], None]] = []

    # the MCU's sensor stream
    def on_sensors(self, packet: Sensors) -> None:
        """A sensor sample: odometry, safety inputs, then one control step."""
        self.latest = packet
        moved = self.odometry.update(packet.hall)
        cal, eps = self.spec.ir_calibrated_m, self.cfg.safety.ir_eps_m
        self.safety.ir_out = [i for i, r in enumerate(packet.ir_m) if abs(r - cal) > eps]
        self.safety.battery_v = packet.battery_v[0]
        self.safety.adhesion = self.adhesion()
        self.apply()
        for callback in self.on_distance:
            callback(moved)
        self._sample.set()
        self._sample = asyncio.Event()

    def on_mcu_fault(self, error: str | None) -> None:
        """The serial line went bad (or recovered)."""
        self.safety.mcu_error = error
        self.apply()

    def on_link(self, up: bool) -> None:
        """The station link went down (stop now) or came back."""
        self.safety.link_up = up
        self.apply()

    def adhesion(self) -> float:
        """Eq. (1)'s margin at the configured inclination; a lifted axle halves the magnets."""
        lifted = sum(self.lifts.values())
        margin = adhesion_margin(self.spec, self.cfg.safety.inclination_deg)
        return margin * (4 - 2 * lifted) / 4

    # the operator
    def drive(
        self, v: float, w: float, sent_ms: float | None = None, key_event: bool = False
    ) -> None:
        """An operator's drive command: it holds for the dead-man time; it takes over from a
        running sweep (which pauses)."""
        self.operator = (v, w)
        self.operator_t = time.monotonic()
        if self.mode == "sweep" and self.sweep_state == "running":
            self.sweep_state = "paused"
        self.mode = "teleop"
        self.apply()
        if sent_ms is not None:
            self.log.command_to_mcu_ms.append(time.time() * 1000 - sent_ms)
            if key_event:
                self.log.key_to_mcu_ms.append(self.log.command_to_mcu_ms[-1])

    def stop(self, estop: bool = False) -> None:
        """Stop (and latch the e-stop); a running sweep pauses."""
        self.operator = (0.0, 0.0)
        if self.sweep_state == "running":
            self.sweep_state = "paused"
        if estop:
            self.safety.estop = True
            try:
                self.mcu.send(PacketType.ESTOP)
            except McuError:
                pass
        self.apply()

    def resume(self) -> None:
        """Release the e-stop latch (the MCU's too)."""
        self.safety.estop = False
        try:
            self.mcu.send(PacketType.RESET_ESTOP)
        except McuError:
            pass

    def set_sweep(self, state: str) -> None:
        """Start, pause, resume or stop the sweep."""
        if state == "running":
            self.mode = "sweep"
            self.operator = (0.0, 0.0)
        self.sweep_state = state
        self.apply()

    # the control step
    def commanded(self) -> tuple[float, float]:
        """What the operator or the sweep asks for now."""
        if self.mode == "teleop":
            if time.monotonic() - self.operator_t > self.cfg.safety.deadman_s:
                if any(self.operator):
                    self.log.deadman_stops += 1
                self.operator = (0.0, 0.0)
            return self.operator
        if self.mode == "sweep" and self.sweep_state == "running":
            return self.auto
        return (0.0, 0.0)

    def apply(self) -> None:
        """Check the commanded motion and send it to the MCU."""
        v, w = self.commanded()
        self.verdict = allowed_motion(v, w, self.safety, self.cfg.safety)
        moving = bool(self.verdict.v or self.verdict.w)
        try:
            if moving:
                self.mcu.drive(
                    *wheel_speeds(self.verdict.v, self.verdict.w, self.spec.track_m),
                    self.cfg.safety.deadman_s,
                )
                self.log.drives_sent += 1
            elif self._moving:
                self.mcu.send(PacketType.STOP)
                self.log.stops_sent += 1
        except McuError:
            moving = False
        self._moving = moving

    # the sweep's pilot
    @property
    def pose(self) -> NDArray[np.float64]:
        """Odometry pose."""
        return self.odometry.pose

    def ir_out(self) -> list[int]:
        """IR sensors that see no surface."""
        return list(self.safety.ir_out)

    def set_heading(self, heading: float) -> None:
        """Correct the odometry heading."""
        self.odometry.set_heading(heading)

    def may_sweep(self) -> bool:
        """Whether the sweep may move now."""
        return self.mode == "sweep" and self.sweep_state == "running" and not self.verdict.halted

    async def step(self, v: float, w: float) -> None:
        """The sweep's motion until the next sensor sample; waits while it may not move."""
        while True:
            if self.sweep_state == "stopped":
                self.auto = (0.0, 0.0)
                raise SweepStopped
            if self.latest is not None and self.latest.faults & Fault.OFF_PLATE:
                self.auto = (0.0, 0.0)
                self.sweep_state = "stopped"
                raise SweepStopped("a wheel left the plate: the MCU refuses to drive")
            self.auto = (v, w)
            if self.may_sweep():
                break
            self.auto = (0.0, 0.0)
            await self.next_sample(0.1)
        await self.next_sample(0.1)

    async def next_sample(self, timeout_s: float) -> None:
        """Wait for the next sensor sample (or ``timeout_s``)."""
        try:
            await asyncio.wait_for(self._sample.wait(), timeout_s)
        except TimeoutError:
            pass

    def flags(self) -> Flag:
        """The MCU's state bits of the latest sample."""
        return self.latest.flags if self.latest is not None else Flag.NONE
