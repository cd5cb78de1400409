"""The simulated robot: skid-steer motion with wheel slip, Hall-sensor odometry, IR edge
sensors with the paper's edge avoidance (Algorithm 1), batteries and adhesion (eq. (1))."""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from processing.poses import integrate_arc, wheel_speeds, wheel_turn

G = 9.81


@dataclass(frozen=True)
class RobotSpec:
    """Physical parameters of the robot (SI units)."""

    track_m: float = 0.20
    wheel_radius_m: float = 0.03
    magnets_per_wheel: int = 36  # paper §2.1; two Hall sensors per wheel, rising and falling edges
    ir_corners_m: tuple[tuple[float, float], ...] = (
        (0.13, -0.09),
        (0.13, 0.09),
        (-0.13, -0.09),
        (-0.13, 0.09),
    )
    ir_calibrated_m: float = 0.03
    ir_max_m: float = 0.5
    ir_noise_m: float = 0.001
    mass_kg: float = 6.5
    magnet_force_per_wheel_kg: float = 14.0  # paper §2.1
    friction: float = 0.6
    com_height_m: float = 0.06
    wheelbase_m: float = 0.26
    slip_sigma: float = 0.02
    turn_slip_sigma: float = 0.03

    @property
    def metres_per_tick(self) -> float:
        """Distance one Hall edge stands for."""
        return 2 * np.pi * self.wheel_radius_m / (4 * self.magnets_per_wheel)


class EdgeAction(enum.Enum):
    """What Algorithm 1 tells the robot to do."""

    none = "none"
    back_off_turn_left = "back_off_turn_left"
    back_off_turn_right = "back_off_turn_right"
    stop_and_wait = "stop_and_wait"


IR_NAMES = ("front_left", "front_right", "rear_left", "rear_right")


def edge_avoidance(
    ranges_m: NDArray[np.floating], calibrated_m: NDArray[np.floating], eps_m: float
) -> tuple[EdgeAction, list[int]]:
    """Paper Algorithm 1: which IR sensors see no surface, and the action to take.

    One sensor out of ``[r_cal - eps, r_cal + eps]``: back off 5 cm and turn away from its
    side; more than one: stop and wait for commands.
    """
    out = [i for i in range(4) if abs(float(ranges_m[i]) - float(calibrated_m[i])) > eps_m]
    if not out:
        return EdgeAction.none, out
    if len(out) > 1:
        return EdgeAction.stop_and_wait, out
    # sensor on the right side (y > 0 in the robot frame: front_right, rear_right) -> turn left
    return (
        EdgeAction.back_off_turn_left if out[0] in (1, 3) else EdgeAction.back_off_turn_right
    ), out


def adhesion_margin(spec: RobotSpec, inclination_deg: float) -> float:
    """F_mag / max(P sin(a)/mu + P cos(a), 2 P d / L) of the paper's eq. (1); > 1 is safe."""
    a = np.radians(inclination_deg)
    P = spec.mass_kg * G
    need = max(
        P * np.sin(a) / spec.friction + P * np.cos(a), 2 * P * spec.com_height_m / spec.wheelbase_m
    )
    return float(4 * spec.magnet_force_per_wheel_kg * G / need)


@dataclass
class Batteries:
    """Main 12 V (3S) and logic 7.4 V (2S) packs discharged by the load."""

    main_v: float = 12.6
    logic_v: float = 8.4

    def drain(self, dt_s: float, moving: bool) -> None:
        """Discharge for ``dt_s`` seconds."""
        self.main_v = max(10.5, self.main_v - dt_s * (0.0009 if moving else 0.0002))
        self.logic_v = max(6.6, self.logic_v - dt_s * 0.0003)


@dataclass
class SimRobot:
    """True pose, odometry pose and sensor state of the robot on a plate."""

    spec: RobotSpec
    rng: np.random.Generator
    pose: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))  # true x, y, yaw
    odom: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))  # Hall odometry
    wheel_ticks: NDArray[np.int64] = field(default_factory=lambda: np.zeros(4, np.int64))
    wheel_speed: NDArray[np.float64] = field(default_factory=lambda: np.zeros(4))
    batteries: Batteries = field(default_factory=Batteries)
    distance_m: float = 0.0
    _tick_rem: NDArray[np.float64] = field(default_factory=lambda: np.zeros(4))

    def step(self, v: float, w: float, dt: float) -> None:
        """Move with commanded speed ``v`` (m/s) and turn rate ``w`` (rad/s) for ``dt`` s."""
        left, right = wheel_speeds(v, w, self.spec.track_m)
        wheel = np.array([left, right, left, right]) * dt  # FL, FR, RL, RR wheel travel
        # Hall sensors count magnet edges of the wheels' rotation
        exact = wheel / self.spec.metres_per_tick + self._tick_rem
        ticks = np.trunc(exact)
        self._tick_rem = exact - ticks
        self.wheel_ticks += ticks.astype(np.int64)
        measured = ticks * self.spec.metres_per_tick
        self.wheel_speed = wheel / dt if dt > 0 else np.zeros(4)
        # odometry: what the wheels say
        d_odo = (measured[[0, 2]].mean() + measured[[1, 3]].mean()) / 2
        th_odo = wheel_turn(measured[[0, 2]].mean(), measured[[1, 3]].mean(), self.spec.track_m)
        self.odom = integrate_arc(self.odom, d_odo, th_odo)
        # truth: the body slips a little against the wheels
        d_true = (left + right) / 2 * dt * (1 - abs(self.rng.normal(0, self.spec.slip_sigma)))
        th_true = w * dt * (1 + self.rng.normal(0, self.spec.turn_slip_sigma))
        self.pose = integrate_arc(self.pose, d_true, th_true)
        self.distance_m += abs(d_true)
        self.batteries.drain(dt, moving=bool(v or w))

    def ir_ranges(
        self, on_plate: Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.bool_]]
    ) -> NDArray[np.float64]:
        """Range (m) each corner IR sensor reads: calibrated over steel, max over an edge."""
        x, y, yaw = self.pose
        c, s = np.cos(yaw), np.sin(yaw)
        corners = np.array(self.spec.ir_corners_m)
        wx = x + c * corners[:, 0] - s * corners[:, 1]
        wy = y + s * corners[:, 0] + c * corners[:, 1]
        over = on_plate(wx, wy)
        noise = self.rng.normal(0, self.spec.ir_noise_m, 4)
        return np.where(over, self.spec.ir_calibrated_m + noise, self.spec.ir_max_m)
