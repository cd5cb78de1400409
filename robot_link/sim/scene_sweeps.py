"""ToF sequences on any structure type (:mod:`robot_link.sim.scenes`), with exact ground
truth, for the map's benchmark and tests.

The robot drives out along the member, across to a second lane, back and across to its
start (:func:`robot_link.sim.tof_sweeps.route`). Each sequence draws its sensor and its
mounting from the seed: resolution and field of view, range noise, the ToF's height,
downward pitch (the top of its view above the surface's horizon: it sees ahead) and
sideways yaw (looking obliquely at members beside the robot). The
robot rocks on welds and bolt heads (roll and pitch up to ``attitude_deg``, height up to
``bump_m``, per cloud); its odometry is the true step between clouds with 6-DoF errors
(``odometry_m`` and ``odometry_deg`` a step: the RMS length of a step's translation and
rotation error, or that much on each axis with ``odometry_per_axis``, √3 times as large),
integrated.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from processing.poses import se2_to_se3
from robot_link.clouds import depth_to_points
from robot_link.sim.scenes import Scene, make_scene
from robot_link.sim.sensors import TofCamera, tof_mount
from robot_link.sim.tof_sweeps import TofSweep, TofSweepConfig, route

# (width, height, horizontal FoV deg, vertical FoV deg, range noise m): ToF cameras of the
# kind climbing robots carry
SENSORS = (
    (224, 172, 62.0, 45.0, 0.01),
    (160, 120, 60.0, 45.0, 0.012),
    (320, 240, 70.0, 55.0, 0.006),
    (176, 132, 56.0, 44.0, 0.008),
)


@dataclass(frozen=True)
class SceneSweepConfig:
    """A structure type, the route's scale and the errors; the rest comes from ``seed``."""

    kind: str = "box_girder"
    seed: int = 0
    clouds: int = 40
    attitude_deg: float = 2.0
    bump_m: float = 0.005
    odometry_m: float = 0.02  # 6-DoF odometry error a step: translation ...
    odometry_deg: float = 2.0  # ... and rotation (RMS length of the error vector)
    odometry_per_axis: bool = False  # True: that much on each axis (a harder case)
    sensor: int | None = None  # index into SENSORS; None: drawn from the seed

    @property
    def odometry_sigmas(self) -> tuple[float, float]:
        """The odometry's error per axis and step: rotation (rad), translation (m)."""
        k = 1.0 if self.odometry_per_axis else 1 / np.sqrt(3)
        return float(np.radians(self.odometry_deg) * k), self.odometry_m * k


def drifting_odometry(
    truth: NDArray[np.float64], cfg: SceneSweepConfig, rng: np.random.Generator
) -> NDArray[np.float64]:
    """The true steps with errors, integrated from the true first pose."""
    out = [truth[0]]
    sigma_rad, sigma_m = cfg.odometry_sigmas
    for k in range(1, len(truth)):
        step = np.linalg.inv(truth[k - 1]) @ truth[k]
        noise = np.eye(4)
        noise[:3, :3] = Rotation.from_rotvec(rng.normal(0, sigma_rad, 3)).as_matrix()
        noise[:3, 3] = rng.normal(0, sigma_m, 3)
        out.append(out[-1] @ step @ noise)
    return np.array(out)


def _camera(cfg: SceneSweepConfig, scene: Scene, rng: np.random.Generator) -> TofCamera:
    """The sequence's ToF camera and mounting, drawn from ``rng`` (the sequence's first draws)."""
    w, h, hfov, vfov, noise = SENSORS[
        cfg.sensor if cfg.sensor is not None else rng.integers(len(SENSORS))
    ]
    fx, fy = (w / 2) / np.tan(np.radians(hfov / 2)), (h / 2) / np.tan(np.radians(vfov / 2))
    mount = tof_mount(
        0.15,
        rng.uniform(0.07, 0.14),
        rng.uniform(8, vfov / 2),
        rng.choice([-1, 1]) * rng.uniform(0, 40),
    )
    return TofCamera(
        scene,
        width=w,
        height=h,
        fx=fx,
        fy=fy,
        noise_sigma_m=noise,
        T_robot_tof=mount,
        noise_along_ray=True,
    )


def scene_camera(cfg: SceneSweepConfig = SceneSweepConfig()) -> TofCamera:
    """The ToF camera (over its structure) that :func:`scene_sweep` records ``cfg`` with."""
    return _camera(cfg, make_scene(cfg.kind, cfg.seed), np.random.default_rng(cfg.seed))


def scene_sweep(cfg: SceneSweepConfig = SceneSweepConfig()) -> TofSweep:
    """Drive the two-lane loop over the structure and record what the ToF camera sees."""
    rng = np.random.default_rng(cfg.seed)
    scene = make_scene(cfg.kind, cfg.seed)
    tof = _camera(cfg, scene, rng)
    noise = tof.noise_sigma_m
    lanes, (x0, x1) = scene.lanes_y_m, scene.x_range_m
    gap = abs(lanes[1] - lanes[0])
    step = (2 * (x1 - x0) + np.pi * gap) / cfg.clouds
    robot = route(TofSweepConfig(lanes_y_m=lanes, x_range_m=(x0, x1), step_m=step, turn_step_deg=0))
    poses = []
    for x, y, yaw in robot[: cfg.clouds]:
        rock = np.eye(4)
        rock[:3, :3] = Rotation.from_euler(
            "xy", rng.uniform(-cfg.attitude_deg, cfg.attitude_deg, 2), degrees=True
        ).as_matrix()
        rock[2, 3] = -rng.uniform(0, cfg.bump_m)
        poses.append(se2_to_se3(x, y, yaw) @ rock @ tof.T_robot_tof)
    truth = np.array(poses)
    odometry = drifting_odometry(truth, cfg, rng)
    clouds = [
        depth_to_points(tof.render(T, rng), tof.fx, tof.fy, tof.cx, tof.cy).astype(np.float32)
        for T in truth
    ]
    length = float(np.sum(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1)))
    intrinsics = {**tof.intrinsics(), "noise_sigma_m": noise}
    return TofSweep(clouds, truth, odometry, length, intrinsics)


def write_sweep(sweep: TofSweep, folder: Path) -> Path:
    """The sequence as a user would hand it to ``steelscan map``: ``folder/clouds/`` with one
    binary PLY per cloud (NaN where no return) and ``sensor.json``, and ``folder/odom.tum``;
    returns the clouds folder."""
    import open3d as o3d

    from processing.poses import format_tum

    clouds = folder / "clouds"
    clouds.mkdir(parents=True, exist_ok=True)
    for i, c in enumerate(sweep.clouds):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(c.astype(np.float64)))
        if not o3d.io.write_point_cloud(clouds / f"c{i:04d}.ply", pcd):
            raise OSError(f"could not write {clouds / f'c{i:04d}.ply'}")
    (clouds / "sensor.json").write_text(
        json.dumps(
            {k: v if k in ("width", "height") else float(v) for k, v in sweep.intrinsics.items()}
        )
    )
    (folder / "odom.tum").write_text(
        format_tum(np.arange(len(sweep.clouds), dtype=float), sweep.odometry)
    )
    return clouds
