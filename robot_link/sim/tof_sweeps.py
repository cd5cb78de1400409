"""ToF sequences with exact ground truth, for mapping benchmarks and tests.

The robot drives lanes along the simulated girder (its web and repeating stiffeners in
view), turns around on a half circle at each lane end and, when asked, comes back to its
start so that the sequence revisits a place. Every ``step_m`` of travel, and in turns every
``turn_step_deg`` of heading (a ToF camera streams: the robot keeps a cloud whenever it
moved or turned enough), the ToF camera takes a depth image (ray cast, with noise); the
odometry integrates each true step with distance and heading errors, as slipping wheels do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from processing.poses import se2_matrix, se2_of_matrix
from robot_link.clouds import depth_to_points
from robot_link.sim.sensors import TofCamera
from robot_link.sim.structure import SteelStructure, make_structure


@dataclass(frozen=True)
class TofSweepConfig:
    """The route and the sensor and odometry errors."""

    lanes_y_m: tuple[float, ...] = (0.56, 0.74)
    x_range_m: tuple[float, float] = (0.15, 1.3)
    step_m: float = 0.04
    revisit: bool = True  # turn back to the start at the end
    noise_sigma_m: float = 0.01
    # relative error of the distance of a step_m step (a random walk in distance)
    odometry_distance_sigma: float = 0.03
    # heading error per step_m driven (a random walk in distance)
    odometry_yaw_sigma_deg: float = 0.6
    girder_overhang_m: float = 1.6  # the girder beyond the plate's ends (0: it ends with the plate)
    # in turns, a cloud every this many degrees of heading too (0: by distance only)
    turn_step_deg: float = 5.0
    seed: int = 0


@dataclass
class TofSweep:
    """Organised clouds (H·W, 3) in the sensor frame, NaN where no return, with the true
    and the odometry sensor poses T_world_tof (N, 4, 4)."""

    clouds: list[NDArray[np.float32]]
    truth: NDArray[np.float64]
    odometry: NDArray[np.float64]
    path_length_m: float
    intrinsics: dict[str, float]


def route(cfg: TofSweepConfig) -> NDArray[np.float64]:
    """Robot poses (x, y, yaw) every ``step_m`` along the lanes and half-circle turns."""
    x0, x1 = cfg.x_range_m
    pieces: list[NDArray[np.float64]] = []
    ys = list(cfg.lanes_y_m) + ([cfg.lanes_y_m[0]] if cfg.revisit else [])
    heading = 0.0
    for k, y in enumerate(ys[:-1] if cfg.revisit else ys):
        forward = k % 2 == 0
        start, end = (x0, x1) if forward else (x1, x0)
        s = np.arange(0, abs(end - start), cfg.step_m)
        xs = start + (s if forward else -s)
        pieces.append(np.column_stack([xs, np.full(len(xs), y), np.full(len(xs), heading)]))
        if k + 1 < len(ys):
            y_next = ys[k + 1]
            r = abs(y_next - y) / 2
            arc_step = (
                cfg.step_m
                if cfg.turn_step_deg <= 0
                else min(cfg.step_m, r * np.radians(cfg.turn_step_deg))
            )
            arc = np.arange(0, np.pi * r, arc_step) / r
            side = 1.0 if y_next > y else -1.0
            turn = side if forward else -side  # turn towards the next lane
            cx, cy = end, (y + y_next) / 2
            angles = heading - np.pi / 2 * side * (1 if forward else -1) + turn * arc
            px = cx + r * np.cos(angles)
            py = cy + r * np.sin(angles)
            pieces.append(np.column_stack([px, py, heading + turn * arc]))
            heading = heading + turn * np.pi
    poses = np.vstack(pieces)
    poses[:, 2] = (poses[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return poses


def drifting_odometry(
    robot: NDArray[np.float64], cfg: TofSweepConfig, rng: np.random.Generator
) -> NDArray[np.float64]:
    """Wheel odometry: each true step (in the robot's frame) with errors, integrated. The
    errors are random walks in the distance driven (a step of ``step_m`` gets the configured
    sigmas), so sampling the route more finely does not add odometry error."""
    out = [robot[0].copy()]
    T = se2_matrix(*robot[0])
    for k in range(1, len(robot)):
        step = np.linalg.inv(se2_matrix(*robot[k - 1])) @ se2_matrix(*robot[k])
        share = max(float(np.linalg.norm(step[:2, 2])), 1e-9) / cfg.step_m
        d = step[:2, 2] * (1 + rng.normal(0, cfg.odometry_distance_sigma) / np.sqrt(share))
        dyaw = np.arctan2(step[1, 0], step[0, 0]) + rng.normal(
            0, np.radians(cfg.odometry_yaw_sigma_deg)
        ) * np.sqrt(share)
        noisy = se2_matrix(d[0], d[1], dyaw)
        T = T @ noisy
        out.append(se2_of_matrix(T))
    return np.array(out)


def tof_sweep(
    cfg: TofSweepConfig = TofSweepConfig(),
    structure: SteelStructure | None = None,
    *,
    clouds: int | None = None,
) -> TofSweep:
    """Drive the route and record what the ToF camera sees; with ``clouds``, only the
    route's first ``clouds`` poses (the same clouds as the whole sweep's first ones)."""
    rng = np.random.default_rng(cfg.seed)
    structure = structure or make_structure(
        cfg.seed, n_cracks=1, n_corrosion=1, girder_overhang_m=cfg.girder_overhang_m
    )
    tof = TofCamera(structure, noise_sigma_m=cfg.noise_sigma_m)
    robot = route(cfg)
    odo = drifting_odometry(robot, cfg, rng)  # drawn for the whole route: the same noise after
    robot, odo = robot[:clouds], odo[:clouds]
    truth = np.array([tof.T_world_tof(p) for p in robot])
    recorded = [
        depth_to_points(tof.render(T, rng), tof.fx, tof.fy, tof.cx, tof.cy).astype(np.float32)
        for T in truth
    ]
    length = float(np.sum(np.linalg.norm(np.diff(robot[:, :2], axis=0), axis=1)))
    return TofSweep(
        recorded, truth, np.array([tof.T_world_tof(p) for p in odo]), length, tof.intrinsics()
    )
