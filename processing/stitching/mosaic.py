"""The mosaic's types: the stitcher's options, where every frame lies (:class:`MosaicLayout`),
rendered bands, the finished mosaic, and the camera's poses from the robot's odometry."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from processing.poses import frame_to_mosaic
from processing.stitching.registration import RegistrationParams

Blend = Literal["feather", "paper", "newest"]
Progress = Callable[[float, str], None]


class FrameSource(Protocol):
    """Frames by index, loaded on demand (a list of arrays is one)."""

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> NDArray[np.uint8]: ...


@dataclass(frozen=True)
class StitchParams:
    """Options of the stitcher."""

    registration: RegistrationParams = field(default_factory=RegistrationParams)
    blend: Blend = "feather"
    tau: float = 0.9  # eq. (2): the new pixel wins where τ·I2 > I1
    median_px: int = 5  # eq. (2): gaps in the new frame's region filled by a median filter
    gain_compensation: bool = True
    flat_field_min_frames: int = 8
    flat_field_sample: int = 16  # frames sampled to estimate the vignetting
    flat_field_min_falloff: float = 0.03  # corrected when the corners are this much darker
    vignetting: bool = True  # estimate the lens falloff from registered overlaps and register again
    vignetting_pairs: int = 300  # pairs sampled for it
    band_bytes: int = 96 * 2**20  # working memory of one band of the mosaic
    cache_bytes: int = 160 * 2**20  # decoded frames kept for reuse


@dataclass
class MosaicLayout:
    """Where every frame goes in the mosaic and how mosaic pixels map to the world.

    ``poses_px`` is (N, 3): frame-centre x, y in mosaic pixels and rotation in radians.
    Mosaic pixel (u, v) is at world ``origin_m + (u, v) / px_per_m``.
    """

    width: int
    height: int
    frame_size: tuple[int, int]  # (w, h)
    channels: int
    px_per_m: float
    origin_m: tuple[float, float]
    poses_px: NDArray[np.float64]
    confident: NDArray[np.bool_]
    gains: NDArray[np.float64]
    pairs: int
    rejected_pairs: int

    def to_world(self, u: float, v: float) -> tuple[float, float]:
        """World (x, y) in metres of a mosaic pixel."""
        return self.origin_m[0] + u / self.px_per_m, self.origin_m[1] + v / self.px_per_m

    def to_mosaic(self, x: float, y: float) -> tuple[float, float]:
        """Mosaic pixel (u, v) of a world point (metres)."""
        return (x - self.origin_m[0]) * self.px_per_m, (y - self.origin_m[1]) * self.px_per_m

    def footprint(self, k: int) -> tuple[int, int, int, int]:
        """Bounding box (x0, y0, x1, y1), end exclusive, of frame k in the mosaic."""
        w, h = self.frame_size
        A = frame_to_mosaic(self.poses_px[k], self.frame_size)
        pts = (
            A[:2] @ np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
        )
        lo, hi = np.floor(pts.min(axis=1)).astype(int), np.ceil(pts.max(axis=1)).astype(int) + 1
        return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


@dataclass
class Band:
    """Rows ``y0 .. y0 + image.shape[0]`` of the mosaic."""

    y0: int
    image: NDArray[np.uint8]
    coverage: NDArray[np.bool_]


@dataclass
class Mosaic:
    """A whole stitched mosaic in memory, with its layout."""

    image: NDArray[np.uint8]
    coverage: NDArray[np.bool_]
    layout: MosaicLayout

    @property
    def frame_poses_px(self) -> NDArray[np.float64]:
        """(N, 3): frame-centre x, y in mosaic pixels and rotation in degrees."""
        p = self.layout.poses_px
        return np.column_stack([p[:, :2], np.degrees(p[:, 2])])

    @property
    def confident(self) -> NDArray[np.bool_]:
        """Frames placed by image registration (False: odometry only)."""
        return self.layout.confident

    def to_world(self, u: float, v: float) -> tuple[float, float]:
        """World (x, y) in metres of a mosaic pixel."""
        return self.layout.to_world(u, v)


def camera_poses(
    robot_poses: NDArray[np.floating], T_robot_camera: Sequence[float], px_per_m: float
) -> NDArray[np.float64]:
    """Camera-centre poses in world pixels from robot odometry (the paper's chain
    image → camera → robot → world: T_ic is the scale ``px_per_m``, T_cr the camera's mount
    (x, y, yaw) on the robot, T_rw the odometry (x, y, yaw))."""
    p = np.asarray(robot_poses, dtype=np.float64).reshape(-1, 3)
    mx, my, myaw = (float(v) for v in T_robot_camera)
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    x = p[:, 0] + c * mx - s * my
    y = p[:, 1] + s * mx + c * my
    return np.column_stack([x * px_per_m, y * px_per_m, p[:, 2] + myaw])
