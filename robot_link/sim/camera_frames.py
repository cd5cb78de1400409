"""The robot's downward camera along a ToF sequence (:mod:`robot_link.sim.scene_sweeps`),
with exact ground truth, so the map's camera fusion is measured on every structure type.

The camera sits under the robot's body looking straight down at the surface it drives on
(the plane z = 0 of every scene; robot frame: x forward, y right, z down). The surface is a
solid texture of the plate, the same wherever it is seen from: mill scale and paint
(value noise over four octaves), rust patches, weld seams across the lanes and stretches of
smooth, low-texture paint. Frames come several times per cloud, at times between the
clouds' (the odometry's clock: cloud i at time i), each seen from the true pose
interpolated on the trajectory, with its own exposure and sensor noise.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from processing.poses import interpolate_poses


@dataclass(frozen=True)
class DownCamera:
    """A downward camera under the robot: pinhole ``width`` x ``height`` px over
    ``hfov_deg``, ``height_m`` above the surface, ``x_m`` ahead of the robot's centre."""

    width: int = 320
    height: int = 240
    hfov_deg: float = 62.0
    height_m: float = 0.09
    x_m: float = 0.02

    @property
    def f(self) -> float:
        """Focal length (px), square pixels."""
        return (self.width / 2) / float(np.tan(np.radians(self.hfov_deg / 2)))

    @property
    def T_robot_camera(self) -> NDArray[np.float64]:
        """The camera's pose on the robot: its axes the robot's (x forward = image right,
        y right = image down, z down = the view)."""
        T = np.eye(4)
        T[:3, 3] = (self.x_m, 0.0, -self.height_m)
        return T

    def intrinsics(self) -> dict[str, float]:
        """``width``, ``height``, ``fx``, ``fy``, ``cx``, ``cy`` (px)."""
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.f,
            "fy": self.f,
            "cx": (self.width - 1) / 2,
            "cy": (self.height - 1) / 2,
        }


@dataclass(frozen=True)
class CameraSweep:
    """Grey frames (H, W) uint8, their times (F,) on the clouds' clock, their true poses
    T_world_camera (F, 4, 4), and ``camera.json`` as the map command reads it."""

    frames: list[NDArray[np.uint8]]
    timestamps: NDArray[np.float64]
    truth: NDArray[np.float64]
    camera: dict[str, object] = field(default_factory=dict)


def _lattice(ix: NDArray[np.int64], iy: NDArray[np.int64], seed: int) -> NDArray[np.float64]:
    """A pseudo-random value in [0, 1) for each integer lattice point (a hash: no table)."""
    h = (ix.astype(np.uint64) * np.uint64(0x9E3779B1)) ^ (
        iy.astype(np.uint64) * np.uint64(0x85EBCA77)
    )
    h ^= np.uint64(seed * 0xC2B2AE3D & 0xFFFFFFFF)
    h ^= h >> np.uint64(15)
    h *= np.uint64(0x2C1B3C6D)
    h ^= h >> np.uint64(12)
    h *= np.uint64(0x297A2D39)
    h ^= h >> np.uint64(15)
    return (h & np.uint64(0xFFFFFF)).astype(np.float64) / float(0x1000000)


def value_noise(
    x: NDArray[np.floating], y: NDArray[np.floating], cell_m: float, seed: int
) -> NDArray[np.float64]:
    """Smooth noise in [0, 1) at world points (metres), varying over ``cell_m``."""
    u, v = np.asarray(x) / cell_m, np.asarray(y) / cell_m
    i, j = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = u - i, v - j
    su, sv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)  # smoothstep
    a, b = _lattice(i, j, seed), _lattice(i + 1, j, seed)
    c, d = _lattice(i, j + 1, seed), _lattice(i + 1, j + 1, seed)
    return (a * (1 - su) + b * su) * (1 - sv) + (c * (1 - su) + d * su) * sv


def plate_texture(
    x: NDArray[np.floating], y: NDArray[np.floating], seed: int
) -> NDArray[np.float64]:
    """Grey level (0-255) of the plate at world points (x, y) in metres."""
    rng = np.random.default_rng(seed)
    fine = sum(
        w * value_noise(x, y, cell, seed + k)
        for k, (cell, w) in enumerate(((0.0006, 0.35), (0.0018, 0.3), (0.006, 0.2), (0.02, 0.15)))
    )
    # smooth paint: the fine octaves fade where a large-scale field is low
    smooth = np.clip((value_noise(x, y, 0.25, seed + 10) - 0.2) / 0.25, 0.15, 1.0)
    grey = 120 + 70 * (fine - 0.5) * smooth
    rust = np.clip((value_noise(x, y, 0.08, seed + 11) - 0.62) / 0.1, 0, 1)
    grey -= 45 * rust * (0.6 + 0.8 * value_noise(x, y, 0.003, seed + 12))
    for xs in rng.uniform(-3, 4, 6):  # weld seams across the lanes, 8 mm wide
        across = np.abs(np.asarray(x) - xs - 0.004 * np.sin(np.asarray(y) * 40))
        bead = np.clip(1 - across / 0.004, 0, 1)
        grey += 50 * bead * (np.sin(np.asarray(y) / 0.0015) * 0.5 + 0.5)
    return np.clip(grey, 0, 255)


class SurfaceView:
    """What the camera sees of a structure: its mesh ray cast (the plane z = 0 where the
    mesh is missed or absent), textured by :func:`plate_texture`."""

    def __init__(self, camera: DownCamera, mesh: o3d.geometry.TriangleMesh | None = None) -> None:
        self.camera = camera
        intr = camera.intrinsics()
        u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
        self.rays = np.stack(
            [(u - intr["cx"]) / camera.f, (v - intr["cy"]) / camera.f, np.ones(u.shape)], -1
        ).reshape(-1, 3)
        self.scene = None
        if mesh is not None:
            self.scene = o3d.t.geometry.RaycastingScene()
            self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))

    def render(self, T_world_camera: NDArray[np.floating], seed: int) -> NDArray[np.float64]:
        """(H, W) grey levels seen from ``T_world_camera``."""
        T = np.asarray(T_world_camera, np.float64)
        d = self.rays @ T[:3, :3].T
        s = -T[2, 3] / d[:, 2]  # to the plane z = 0
        if self.scene is not None:
            origins = np.broadcast_to(T[:3, 3], d.shape)
            rays = np.hstack([origins, d]).astype(np.float32)
            tensor = o3d.core.Tensor(rays)  # type: ignore[call-overload]  # stubs lack defaults
            hit = self.scene.cast_rays(tensor)["t_hit"].numpy().astype(np.float64)
            s = np.where(np.isfinite(hit), hit, s)
        x, y = T[0, 3] + s * d[:, 0], T[1, 3] + s * d[:, 1]
        return plate_texture(x, y, seed).reshape(self.camera.height, self.camera.width)


def camera_sweep(
    tof_truth: NDArray[np.floating],
    T_robot_tof: NDArray[np.floating],
    seed: int,
    mesh: o3d.geometry.TriangleMesh | None = None,
    camera: DownCamera = DownCamera(),
    overlap: float = 0.7,
) -> CameraSweep:
    """Frames of the structure ``mesh`` (the plane z = 0 without) along the ToF poses
    ``tof_truth`` (N, 4, 4; cloud i at time i), as often as keeps ``overlap`` of a frame's
    short side between consecutive frames."""
    view = SurfaceView(camera, mesh)
    rng = np.random.default_rng(seed + 7919)
    truth_tof = np.asarray(tof_truth, np.float64)
    T_tof_camera = np.linalg.inv(np.asarray(T_robot_tof)) @ camera.T_robot_camera
    steps = np.linalg.norm(np.diff(truth_tof[:, :3, 3], axis=0), axis=1)
    short_m = camera.height_m * camera.height / camera.f  # the footprint's short side
    per_cloud = max(1, int(np.ceil(float(np.max(steps)) / ((1 - overlap) * short_m))))
    times = np.arange(0, (len(truth_tof) - 1) * per_cloud + 1) / per_cloud
    poses = interpolate_poses(np.arange(len(truth_tof), dtype=float), truth_tof, times)
    truth = poses @ T_tof_camera
    frames = []
    gain = 1.0
    for T in truth:
        gain = float(np.clip(gain + rng.normal(0, 0.03), 0.8, 1.2))  # auto-exposure wander
        image = gain * view.render(T, seed) + rng.normal(0, 2.0, (camera.height, camera.width))
        frames.append(np.clip(np.rint(image), 0, 255).astype(np.uint8))
    info: dict[str, object] = {
        **camera.intrinsics(),
        "T_tof_camera": T_tof_camera.tolist(),
        "timestamps": [round(float(t), 6) for t in times],
    }
    return CameraSweep(frames, times, truth, info)


def write_frames(sweep: CameraSweep, folder: Path) -> Path:
    """The frames as the map command reads them: ``folder/frame_00000.png`` ... and
    ``folder/camera.json``; returns ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for k, frame in enumerate(sweep.frames):
        if not cv2.imwrite(str(folder / f"frame_{k:05d}.png"), frame):
            raise OSError(f"could not write {folder / f'frame_{k:05d}.png'}")
    (folder / "camera.json").write_text(json.dumps(sweep.camera))
    return folder
