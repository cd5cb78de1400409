"""The downward camera's motion for the ``map`` job: the session's frames as the map's
camera factors (:mod:`processing.mapping.planar_camera`), beside the ToF's registrations
and the odometry in one pose graph.

The frames' motion is the mosaic's where the stitch job placed them (each frame pair both
placed by image registration: the mosaic's placement holds every overlap, lane to lane
too), else consecutive frames registered pair by pair here
(:func:`processing.mapping.frame_pairs.frame_deltas`)."""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Sequence
from typing import Any, overload

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.mapping.camera_motion import CameraFactors
from processing.mapping.planar_camera import camera_height, downward_camera, planar_factors
from processing.poses import relative_se2
from processing.stitching.mosaic import camera_poses
from server.jobs.context import JobContext
from server.storage.models import Frame

Delta = NDArray[np.float64] | None


class _GreyFrames(Sequence[NDArray[np.uint8]]):
    """The session's frames as grey images, decoded when asked for (one pair in memory);
    one that cannot be read is blank (its pairs do not register)."""

    def __init__(self, ctx: JobContext, frames: list[Frame], size: tuple[int, int]) -> None:
        self.ctx, self.frames, self.size = ctx, frames, size

    def __len__(self) -> int:
        return len(self.frames)

    @overload
    def __getitem__(self, k: int) -> NDArray[np.uint8]: ...
    @overload
    def __getitem__(self, k: slice) -> list[NDArray[np.uint8]]: ...
    def __getitem__(self, k: int | slice) -> Any:
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        w, h = self.size
        try:
            data = self.ctx.files.payload(self.frames[k])
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
        except (OSError, ValueError):
            image = None
        if image is None or image.shape != (h, w):
            return np.zeros((h, w), np.uint8)
        return image


def _mosaic_deltas(ctx: JobContext, frames: list[Frame]) -> list[Delta] | None:
    """Each consecutive frame pair's motion (dx, dy px, dθ) in the mosaic (None where either
    frame was not placed by registration); None without a mosaic of these frames."""
    path = ctx.results_dir() / "mosaic.json"
    try:
        world = json.loads(path.read_text())
        placed = {
            f["frame"]: np.array([f["x"], f["y"], np.radians(f["theta_deg"])], np.float64)
            for f in world.get("frames", [])
            if f.get("confident")
        }
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if sum(f.seq in placed for f in frames) < 2:
        return None
    return [
        relative_se2(placed[a.seq], placed[b.seq]) if a.seq in placed and b.seq in placed else None
        for a, b in zip(frames[:-1], frames[1:])
    ]


def _odometry_deltas(
    frames: list[Frame], calib: dict[str, Any], px_per_m: float
) -> list[NDArray[np.float64]] | None:
    """Each consecutive frame pair's motion (dx, dy px, dθ) as the odometry puts the camera
    (the registration's start where the frames overlap too little for phase correlation to
    find it); None where a frame has no pose."""
    if any(f.pose_x is None for f in frames):
        return None
    robot = np.array([[f.pose_x, f.pose_y, f.pose_yaw] for f in frames], np.float64)
    cameras = camera_poses(robot, calib.get("T_robot_camera", [0.0, 0.0, 0.0]), px_per_m)
    return [relative_se2(a, b) for a, b in zip(cameras[:-1], cameras[1:])]


def session_camera(
    ctx: JobContext, cloud_times: NDArray[np.float64], T_robot_tof: NDArray[np.float64]
) -> tuple[CameraFactors, dict[str, Any]] | None:
    """The camera factors of the clouds at ``cloud_times`` and what the job's result says
    of them; None where the session has no calibrated camera or fewer than two frames."""
    calib = ctx.session().calibration.get("camera", {})
    px_per_m = float(calib.get("px_per_m") or 0.0)
    if px_per_m <= 0:
        return None
    with ctx.factory() as db:
        rows = list(db.scalars(ctx.rows(Frame)))
    frames: list[Frame] = []
    for f in sorted(rows, key=lambda f: (f.timestamp, f.seq)):
        if not frames or f.timestamp > frames[-1].timestamp:  # one frame an instant
            frames.append(f)
    if len(frames) < 2:
        return None
    size = Counter((f.width, f.height) for f in frames).most_common(1)[0][0]
    deltas = _mosaic_deltas(ctx, frames)
    source = "mosaic"
    if deltas is None:
        from processing.mapping.frame_pairs import frame_deltas

        predicted = _odometry_deltas(frames, calib, px_per_m)
        deltas = frame_deltas(_GreyFrames(ctx, frames, size), predicted)
        source = "frames"
    height_m = camera_height(size[0], px_per_m, calib.get("height_m"))
    model = downward_camera(
        size[0],
        size[1],
        px_per_m,
        calib.get("T_robot_camera", [0.0, 0.0, 0.0]),
        T_robot_tof,
        height_m,
    )
    times = np.array([f.timestamp for f in frames], np.float64)
    factors = planar_factors(deltas, times, cloud_times, model, height_m)
    report = {
        "source": source,
        "frames": len(frames),
        "frame_pairs_linked": sum(d is not None for d in deltas),
        "frame_pairs": len(deltas),
        "cloud_steps_linked": sum(s is not None for s in factors.steps),
        "height_m": round(height_m, 4),
    }
    return factors, report
