"""The station's downward camera as the map's camera factors (:mod:`.camera_motion`).

A session's calibration states the camera as the stitcher uses it: its image size, its
scale ``px_per_m`` on the surface and its planar mount on the robot (x, y, θ, image x along
θ). Its frames' motion (the mosaic's placement of each frame, or consecutive frames
registered pair by pair) is a planar step in that image's pixels. As a camera model for the
pose graph it is a pinhole looking straight down from its mount, ``height_m`` over the
surface the robot drives on (the calibration's, else the footprint's length: a lens of
about 80° across), with the focal length that gives ``px_per_m`` there; the height only
ties a tilt to the foot's motion, the scale is the calibrated one. The image's y axis lies
to the robot's left, as the mosaic lays frames out, while a camera looking down has its y
to the right: a step (dx, dy, dθ) in the image is (dx, -dy, -dθ) in the camera's
footprint frame.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from processing.mapping.camera_motion import (
    CameraFactors,
    CameraModel,
    CameraParams,
    cloud_steps,
    foot_steps_px_to_m,
    with_scale_error,
)
from processing.poses import se2_to_se3

# the mosaic's image axes (x along the heading, y to the left) in a camera looking down
_LOOKING_DOWN = np.diag([1.0, -1.0, -1.0])


def downward_camera(
    width: int,
    height: int,
    px_per_m: float,
    T_robot_camera: Sequence[float],
    T_robot_tof: NDArray[np.floating],
    height_m: float | None = None,
) -> CameraModel:
    """The pinhole model (module docstring) of a camera of ``width`` x ``height`` px seeing
    ``px_per_m`` on the surface, mounted at ``T_robot_camera`` (x, y, θ) on a robot whose
    ToF sits at ``T_robot_tof`` (4, 4)."""
    h = camera_height(width, px_per_m, height_m)
    x, y, yaw = (float(v) for v in T_robot_camera)
    mount = se2_to_se3(x, y, yaw, z=h)
    mount[:3, :3] = mount[:3, :3] @ _LOOKING_DOWN
    T_tof_camera = np.linalg.inv(np.asarray(T_robot_tof, np.float64)) @ mount
    f = px_per_m * h
    return CameraModel(
        int(width), int(height), f, f, (width - 1) / 2, (height - 1) / 2, T_tof_camera
    )


def camera_height(width: int, px_per_m: float, height_m: float | None = None) -> float:
    """The camera's height over the surface: ``height_m`` where calibrated, else its
    footprint's length (``width`` / ``px_per_m``)."""
    return float(height_m) if height_m else width / px_per_m


def planar_factors(
    deltas_px: Sequence[NDArray[np.floating] | None],
    frame_times: NDArray[np.floating],
    cloud_times: NDArray[np.floating],
    camera: CameraModel,
    height_m: float,
    params: CameraParams = CameraParams(),
) -> CameraFactors:
    """The map's camera factors from the frames' planar motion ``deltas_px`` (N_f - 1; each
    (dx, dy px, dθ) of frame k + 1 in frame k's image, None where unknown) at
    ``frame_times`` (N_f,), chained to the clouds at ``cloud_times`` (N,, the same clock),
    for ``camera`` (:func:`downward_camera`) ``height_m`` over the surface, as sure of
    their scale as ``params.sigma_scale``."""
    flipped = [None if d is None else np.array([d[0], -d[1], -d[2]], np.float64) for d in deltas_px]
    distances = np.full(len(frame_times), float(height_m))
    steps = foot_steps_px_to_m(flipped, distances, camera, params)
    chained = cloud_steps(np.asarray(frame_times, np.float64), steps, cloud_times)
    return CameraFactors(
        camera,
        [with_scale_error(s, params.sigma_scale) for s in chained],
        np.full(len(cloud_times), float(height_m)),
        params.sigma_scale,
    )
