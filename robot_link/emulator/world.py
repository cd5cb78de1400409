"""The emulated robot and the plate it stands on: geometry, sensors and the seed's layout.

The plate frame has its origin at a corner of the plate, x along its width, y along its
height; heading 0 faces +x, π/2 faces +y (``steelscan mcu-emulator``'s header).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from robot_link.sim.robot import RobotSpec, SimRobot
from robot_link.sim.sensors import DownwardCamera, TofCamera, tof_mount
from robot_link.sim.structure import SteelStructure, make_structure

# the emulated robot: wheels 8 cm from its centre each way, an IR sensor 4 cm ahead of
# (or behind) each wheel, so a sensor sees the edge well before a wheel reaches it
EMULATED_ROBOT = RobotSpec(
    track_m=0.16,
    wheelbase_m=0.16,
    ir_corners_m=((0.12, -0.10), (0.12, 0.10), (-0.12, -0.10), (-0.12, 0.10)),
)
OUTLINE_M = (0.28, 0.24)  # length along the heading, width across
# the inspection camera sits at the robot's centre, turned so its 600 px image x runs along
# the heading and its 800 px image y across: 0.5 mm per pixel, 0.30 m x 0.40 m of plate
EMULATED_CAMERA = DownwardCamera(width=600, height=800, footprint_x_m=0.30, mount_x_m=0.0)


@dataclass
class World:
    """The plate (with its painted defects), the robot on it and its sensors."""

    seed: int
    structure: SteelStructure
    robot: SimRobot
    camera: DownwardCamera = EMULATED_CAMERA
    tof: TofCamera = field(init=False)
    inclination_deg: float = 90.0

    def __post_init__(self) -> None:
        self.tof = TofCamera(self.structure, T_robot_tof=tof_mount(x_m=0.13))

    @property
    def spec(self) -> RobotSpec:
        """The robot's physical parameters."""
        return self.robot.spec

    def wheels_on_plate(self, pose: NDArray[np.floating] | None = None) -> bool:
        """Whether all four wheels' contact points are on the plate."""
        x, y, yaw = self.robot.pose if pose is None else pose
        c, s = np.cos(yaw), np.sin(yaw)
        ax, ay = self.spec.wheelbase_m / 2, self.spec.track_m / 2
        wx = np.array([ax, ax, -ax, -ax])
        wy = np.array([-ay, ay, -ay, ay])
        return bool(self.structure.on_plate(x + c * wx - s * wy, y + s * wx + c * wy).all())

    def header(self) -> dict[str, object]:
        """The emulator's header line: plate, robot outline and camera footprint (metres)."""
        w, h = self.structure.plate_size_m
        fx, fy = self.camera.footprint_m
        return {
            "plate": {"width": w, "height": h},
            "robot": {"length": OUTLINE_M[0], "width": OUTLINE_M[1]},
            "camera_footprint": {"width": round(fy, 4), "height": round(fx, 4)},
            "m_per_px": self.camera.m_per_px,
            "seed": self.seed,
        }


def make_world(seed: int, plate_size_m: tuple[float, float] | None = None) -> World:
    """The plate and start pose for ``seed``: a plate 1.0-1.8 m by 0.6-1.1 m (unless
    ``plate_size_m``) with cracks and rust patches over it, and the robot set down on it
    roughly square to its edges (within 4°), as an operator places it."""
    rng = np.random.default_rng(seed)
    if plate_size_m is None:
        plate_size_m = (round(rng.uniform(1.0, 1.8), 2), round(rng.uniform(0.6, 1.1), 2))
    w, h = plate_size_m
    if w < 0.6 or h < 0.5:
        raise ValueError(
            f"a plate of {w} x {h} m is too small for the robot (0.6 x 0.5 m at least)"
        )
    area = w * h
    structure = make_structure(
        seed,
        plate_size_m=(w, h),
        n_cracks=max(2, round(4 * area)),
        n_corrosion=max(1, round(2 * area)),
        defect_region_m=(0.08, 0.08, w - 0.08, h - 0.08),
        girder_overhang_m=0.8,
    )
    start = np.array(
        [
            rng.uniform(0.3, w - 0.3),
            rng.uniform(0.25, h - 0.25),
            np.radians(rng.uniform(-4.0, 4.0)),
        ]
    )
    robot = SimRobot(EMULATED_ROBOT, np.random.default_rng(seed + 1), pose=start, odom=start.copy())
    return World(seed, structure, robot)
