"""The MCU's firmware logic: commands in, wheel speeds out, with its own safety layer.

The MCU stops the wheels by itself, whatever the host says: a drive command holds for at
most ``deadman_s`` (the dead-man), an e-stop latches until reset, no wheel turns forward
while a front IR sensor sees no surface (nor backward at the rear; the paper's Algorithm 1
guard), and it refuses to drive on a low battery or when the adhesion margin of eq. (1)
falls below its limit. Wheel speeds ramp up at ``accel_mps2`` and down at ``brake_mps2``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from processing.poses import wheel_turn
from robot_link.emulator.world import World
from robot_link.mcu.packets import (
    PROTOCOL_VERSION,
    Ack,
    AckStatus,
    Drive,
    Fault,
    Flag,
    HelloReply,
    Lift,
    PacketError,
    PacketType,
    Sensors,
    hello_version,
)
from robot_link.sim.robot import adhesion_margin

FRONT, REAR = (0, 1), (2, 3)  # IR sensor indices (IR_NAMES order)


@dataclass(frozen=True)
class FirmwareParams:
    """Limits the firmware enforces."""

    deadman_s: float = 0.2
    max_wheel_mps: float = 0.25
    accel_mps2: float = 1.5
    brake_mps2: float = 3.0  # slowing down: the motors brake harder than they accelerate
    ir_eps_m: float = 0.02
    min_battery_v: float = 10.8
    min_adhesion: float = 1.5
    sensor_hz: int = 50


@dataclass
class Firmware:
    """The MCU's state; :meth:`handle` takes the host's packets, :meth:`tick` runs the
    control loop and physics for one period."""

    world: World
    params: FirmwareParams = FirmwareParams()
    info: dict[str, object] = field(default_factory=dict)
    t_s: float = 0.0
    target: tuple[float, float] = (0.0, 0.0)  # commanded wheel speeds (left, right)
    wheels: tuple[float, float] = (0.0, 0.0)  # wheel speeds now
    hold_until: float = 0.0
    estop: bool = False
    lifts: dict[str, bool] = field(default_factory=lambda: {"front": False, "rear": False})
    flags: Flag = Flag.NONE
    faults: Fault = Fault.NONE
    host_garbled: int = 0
    last_drive_t: float | None = None  # when the last DRIVE arrived (emulator clock)

    def handle(self, ptype: int, seq: int, body: bytes) -> tuple[PacketType, bytes]:
        """The reply (type, body) to the host's packet ``seq``."""
        try:
            kind = PacketType(ptype)
        except ValueError:
            return PacketType.ACK, Ack(seq, AckStatus.UNKNOWN_TYPE).pack()
        try:
            if kind is PacketType.HELLO:
                if hello_version(body) != PROTOCOL_VERSION:
                    return PacketType.ACK, Ack(seq, AckStatus.WRONG_VERSION).pack()
                reply = HelloReply(PROTOCOL_VERSION, self.params.sensor_hz, self.info)
                return PacketType.HELLO_REPLY, reply.pack()
            return PacketType.ACK, Ack(seq, self._command(kind, body)).pack()
        except PacketError:
            return PacketType.ACK, Ack(seq, AckStatus.BAD_ARGUMENT).pack()

    def _command(self, kind: PacketType, body: bytes) -> AckStatus:
        if kind is PacketType.DRIVE:
            return self._drive(Drive.unpack(body))
        if kind is PacketType.LIFT:
            lift = Lift.unpack(body)
            self.lifts[lift.axle] = lift.up
        elif kind is PacketType.STOP:
            self.target, self.hold_until = (0.0, 0.0), self.t_s
        elif kind is PacketType.ESTOP:
            self.estop = True
            self.target = self.wheels = (0.0, 0.0)
        elif kind is PacketType.RESET_ESTOP:
            self.estop = False
        else:
            return AckStatus.UNKNOWN_TYPE
        return AckStatus.OK

    def _drive(self, cmd: Drive) -> AckStatus:
        self.last_drive_t = self.t_s
        if self.estop:
            return AckStatus.ESTOP_LATCHED
        if not self.world.wheels_on_plate():
            return AckStatus.OFF_PLATE
        if self.world.robot.batteries.main_v < self.params.min_battery_v:
            return AckStatus.LOW_BATTERY
        if self.adhesion() < self.params.min_adhesion:
            return AckStatus.ADHESION
        if not (np.isfinite(cmd.left_mps) and np.isfinite(cmd.right_mps)):
            return AckStatus.BAD_ARGUMENT
        top = self.params.max_wheel_mps
        self.target = (
            float(np.clip(cmd.left_mps, -top, top)),
            float(np.clip(cmd.right_mps, -top, top)),
        )
        self.hold_until = self.t_s + min(cmd.hold_s, self.params.deadman_s)
        return AckStatus.OK

    def adhesion(self) -> float:
        """Eq. (1)'s margin at the plate's inclination; lifting an axle halves the magnets."""
        lifted = sum(self.lifts.values())
        return adhesion_margin(self.world.spec, self.world.inclination_deg) * (4 - 2 * lifted) / 4

    def tick(self, dt: float) -> None:
        """Run the control loop and the physics for ``dt`` seconds."""
        self.t_s += dt
        flags, faults = Flag.NONE, Fault.NONE
        left, right = self.target
        if self.t_s > self.hold_until and (left or right):
            left = right = 0.0
            self.target = (0.0, 0.0)
            flags |= Flag.DEADMAN_STOPPED
            faults |= Fault.DEADMAN
        if self.estop:
            left = right = 0.0
            flags |= Flag.ESTOP_LATCHED
            faults |= Fault.ESTOP
        left, right, edge = self._edge_guard(left, right)
        flags |= edge
        if edge:
            faults |= Fault.EDGE
        on_plate = self.world.wheels_on_plate()
        if not on_plate:
            left = right = 0.0
            self.wheels = (0.0, 0.0)
            faults |= Fault.OFF_PLATE
        self.wheels = (self._ramp(self.wheels[0], left, dt), self._ramp(self.wheels[1], right, dt))
        if self.estop:
            self.wheels = (0.0, 0.0)  # the e-stop cuts the motors' power: no ramp
        v = (self.wheels[0] + self.wheels[1]) / 2
        w = wheel_turn(self.wheels[0], self.wheels[1], self.world.spec.track_m)
        if on_plate:
            self.world.robot.step(v, w, dt)
        if self.world.robot.batteries.main_v < self.params.min_battery_v:
            faults |= Fault.LOW_BATTERY
        if self.adhesion() < self.params.min_adhesion:
            faults |= Fault.ADHESION
        if any(self.wheels):
            flags |= Flag.MOVING
        flags |= Flag.FRONT_LIFT_UP if self.lifts["front"] else Flag.NONE
        flags |= Flag.REAR_LIFT_UP if self.lifts["rear"] else Flag.NONE
        self.flags, self.faults = flags, faults

    def _ramp(self, now: float, target: float, dt: float) -> float:
        slowing = abs(target) < abs(now) or target * now < 0
        step = (self.params.brake_mps2 if slowing else self.params.accel_mps2) * dt
        return float(now + np.clip(target - now, -step, step))

    def _edge_guard(self, left: float, right: float) -> tuple[float, float, Flag]:
        """Algorithm 1's guard: the translation towards a side whose IR sensor sees no
        surface is cut; turning in place stays allowed; three sensors out stop everything."""
        out = self.ir_out()
        if len(out) >= 3:
            return 0.0, 0.0, Flag.BLOCKED_FORWARD | Flag.BLOCKED_REVERSE
        v, half_diff = (left + right) / 2, (right - left) / 2
        flag = Flag.NONE
        if v > 0 and any(i in out for i in FRONT):
            v, flag = 0.0, Flag.BLOCKED_FORWARD
        elif v < 0 and any(i in out for i in REAR):
            v, flag = 0.0, Flag.BLOCKED_REVERSE
        return v - half_diff, v + half_diff, flag

    def ir_out(self) -> list[int]:
        """The IR sensors that see no surface now."""
        ranges = self.world.robot.ir_ranges(self.world.structure.on_plate)
        cal = self.world.spec.ir_calibrated_m
        return [i for i in range(4) if abs(float(ranges[i]) - cal) > self.params.ir_eps_m]

    def sensors(self) -> Sensors:
        """One SENSORS sample."""
        r = self.world.robot
        ranges = r.ir_ranges(self.world.structure.on_plate)
        speeds = [self.wheels[0], self.wheels[1], self.wheels[0], self.wheels[1]]
        current = tuple(0.15 + 1.2 * abs(s) for s in speeds) if any(speeds) else (0.02,) * 4
        ticks = tuple(int(t) for t in r.wheel_ticks)
        return Sensors(
            t_ms=int(self.t_s * 1000),
            hall=(ticks[0], ticks[1], ticks[2], ticks[3]),
            ir_m=(float(ranges[0]), float(ranges[1]), float(ranges[2]), float(ranges[3])),
            battery_v=(r.batteries.main_v, r.batteries.logic_v),
            current_a=(current[0], current[1], current[2], current[3]),
            faults=self.faults | (Fault.HOST_GARBLED if self.host_garbled else Fault.NONE),
            flags=self.flags,
        )
