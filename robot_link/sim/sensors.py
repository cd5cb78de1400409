"""Simulated sensors: the downward inspection camera and the ToF depth camera."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, cast

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from robot_link.sim.imaging import warp_affine_exact
from robot_link.sim.structure import SteelStructure


@dataclass(frozen=True)
class DownwardCamera:
    """Camera looking at the surface; image x along the robot's heading (paper §3.1)."""

    width: int = 640
    height: int = 480
    footprint_x_m: float = 0.18  # along the heading: the paper's 18 cm x 14 cm
    mount_x_m: float = -0.12  # behind the robot's centre ("camera at the back")
    gain_range: tuple[float, float] = (0.9, 1.1)
    noise_sigma: float = 2.0
    jpeg_quality: int = 90

    @property
    def m_per_px(self) -> float:
        """Metres of surface per image pixel (square pixels)."""
        return self.footprint_x_m / self.width

    @property
    def footprint_m(self) -> tuple[float, float]:
        """Covered surface (along, across) in metres."""
        return self.footprint_x_m, self.height * self.m_per_px

    def capture_spacing_m(self, min_overlap: float) -> float:
        """Largest whole-centimetre spacing that keeps ``min_overlap`` between shots."""
        return float(np.floor(self.footprint_x_m * (1 - min_overlap) * 100 + 1e-9) / 100)

    def pose_in_world(self, robot_pose: NDArray[np.floating]) -> NDArray[np.float64]:
        """Camera centre (x, y, yaw) on the surface for a robot pose."""
        x, y, yaw = robot_pose
        return np.array([x + self.mount_x_m * np.cos(yaw), y + self.mount_x_m * np.sin(yaw), yaw])

    def render(
        self,
        structure: SteelStructure,
        cam_pose: NDArray[np.floating],
        rng: np.random.Generator,
        *,
        exact: bool = False,
    ) -> NDArray[np.uint8]:
        """BGR image of the surface under the camera at ``cam_pose`` (x, y, yaw); ``exact``:
        interpolated at the exact sub-pixel position (:func:`warp_affine_exact`, ~20 ms, for
        the frames that are stitched and scored), else by OpenCV (which rounds positions to
        1/32 px: the live preview)."""
        x, y, yaw = cam_pose
        c, s = np.cos(yaw), np.sin(yaw)
        k = self.m_per_px / structure.m_per_px
        cx, cy = (self.width - 1) / 2, (self.height - 1) / 2
        A = np.array([[c, -s], [s, c]]) * k
        t = np.array([x, y]) / structure.m_per_px - A @ (cx, cy)
        M = np.hstack([A, t[:, None]])
        img: NDArray[np.float32] | NDArray[np.uint8]
        if exact:
            img = warp_affine_exact(structure.texture, M, (self.width, self.height), border=25.0)
        else:
            img = cast(
                NDArray[np.uint8],
                cv2.warpAffine(
                    structure.texture,
                    M,
                    (self.width, self.height),
                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                    borderMode=cv2.BORDER_CONSTANT,
                    borderValue=(25, 25, 25),
                ),
            )
        gain = rng.uniform(*self.gain_range)
        yy, xx = np.mgrid[0 : self.height, 0 : self.width].astype(np.float32)
        vignette = 1 - 0.15 * (((xx - cx) / cx) ** 2 + ((yy - cy) / cy) ** 2) / 2
        out = img.astype(np.float32) * (gain * vignette)[..., None]
        out += rng.normal(0, self.noise_sigma, out.shape).astype(np.float32)
        return np.clip(out, 0, 255).astype(np.uint8)

    def encode(self, image: NDArray[np.uint8]) -> bytes:
        """JPEG bytes of a frame."""
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        return buf.tobytes()


def tof_mount(
    x_m: float = 0.15, height_m: float = 0.10, pitch_deg: float = 20.0, yaw_deg: float = 0.0
) -> NDArray[np.float64]:
    """T_robot_tof: ToF at the front, looking ahead and tilted ``pitch_deg`` down to the
    surface, turned ``yaw_deg`` towards the robot's right (obliquely at members beside it).

    Robot frame: x forward, y right, z down into the surface; sensor frame: x right,
    y down, z forward.
    """
    p = np.radians(pitch_deg)
    T = np.eye(4)
    T[:3, 0] = (0, 1, 0)
    T[:3, 1] = (-np.sin(p), 0, np.cos(p))
    T[:3, 2] = (np.cos(p), 0, np.sin(p))
    T[:3, 3] = (x_m, 0, -height_m)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    turn = np.eye(4)
    turn[:2, :2] = [[c, -s], [s, c]]  # about the robot's z (down): towards +y, its right
    return turn @ T


class HasMesh(Protocol):
    """A structure or scene: anything with a triangle mesh to ray cast."""

    mesh: o3d.geometry.TriangleMesh


@dataclass
class TofCamera:
    """A 224 x 172 time-of-flight camera rendered by ray casting the structure's mesh; its
    noise (``noise_sigma_m``) is on the range along each ray (``noise_along_ray``) or on
    the depth."""

    structure: HasMesh
    width: int = 224
    height: int = 172
    fx: float = 195.0
    fy: float = 195.0
    noise_sigma_m: float = 0.01
    max_range_m: float = 4.0
    T_robot_tof: NDArray[np.float64] = field(default_factory=tof_mount)
    noise_along_ray: bool = False

    def __post_init__(self) -> None:
        self.cx, self.cy = (self.width - 1) / 2, (self.height - 1) / 2
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(self.structure.mesh))
        u, v = np.meshgrid(np.arange(self.width), np.arange(self.height))
        d = np.stack(
            [(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u, float)], -1
        ).reshape(-1, 3)
        self._dir_norm = np.linalg.norm(d, axis=1)
        self._dirs = d / self._dir_norm[:, None]

    def intrinsics(self) -> dict[str, float]:
        """Pinhole parameters for the wire."""
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
        }

    def T_world_tof(self, robot_pose: NDArray[np.floating]) -> NDArray[np.float64]:
        """Sensor pose in the world for a planar robot pose."""
        x, y, yaw = robot_pose
        T = np.eye(4)
        T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        T[:2, 3] = (x, y)
        return T @ self.T_robot_tof

    def surface(
        self, T_world_tof: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """What each pixel's ray truly hits from ``T_world_tof``, without noise, in the world:
        points, unit surface normals and unit ray directions, (K, 3) each, for the K pixels
        with a return."""
        R, t = T_world_tof[:3, :3], T_world_tof[:3, 3]
        dirs = self._dirs @ R.T
        rays = np.hstack([np.broadcast_to(t, dirs.shape), dirs]).astype(np.float32)
        tensor = o3d.core.Tensor(rays)  # type: ignore[call-overload]  # Open3D's stubs lack dtype/device defaults
        hits = self._scene.cast_rays(tensor)
        hit = hits["t_hit"].numpy().astype(np.float64)
        ok = np.isfinite(hit) & (hit <= self.max_range_m)
        normals = hits["primitive_normals"].numpy()[ok].astype(np.float64)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return t + dirs[ok] * hit[ok, None], normals, dirs[ok]

    def render(
        self, T_world_tof: NDArray[np.float64], rng: np.random.Generator
    ) -> NDArray[np.float32]:
        """(H, W) depth image in metres (z along the optical axis), NaN where no return."""
        R, t = T_world_tof[:3, :3], T_world_tof[:3, 3]
        dirs = self._dirs @ R.T
        rays = np.hstack([np.broadcast_to(t, dirs.shape), dirs]).astype(np.float32)
        tensor = o3d.core.Tensor(rays)  # type: ignore[call-overload]  # Open3D's stubs lack dtype/device defaults
        hit = self._scene.cast_rays(tensor)["t_hit"].numpy()
        noise = rng.normal(0, self.noise_sigma_m, hit.shape)
        if self.noise_along_ray:
            z = (
                hit + noise
            ) / self._dir_norm  # range along the ray -> depth along the optical axis
        else:
            z = hit / self._dir_norm + noise
        z[~np.isfinite(hit) | (hit > self.max_range_m)] = np.nan
        return z.reshape(self.height, self.width).astype(np.float32)
