"""The downward camera's motion as pose-graph factors beside the ToF's.

Consecutive frames are registered as the stitcher registers them (:mod:`.frame_pairs`:
sub-pixel translation and rotation). What a pair measures is where the second frame's
optical axis meets the surface in the first frame's image, and the turn about the
surface's normal: the *footprint frame* F (the axis' foot on the surface, the image's
heading) moves by a planar step (x, y, ψ) in metres, scaled from pixels by the distance to
the surface along the optical axis, which the ToF measures (the plane of the surface in
its cloud, carried into the camera's frame). Footprint steps compose exactly in SE(2), so
frames taken at their own times are chained and interpolated to the clouds' times (never
paired by index): a cloud pair's step F(tᵢ₋₁)⁻¹ F(tᵢ) with the chain's covariance, and
the scale's error along it, as large as the route's measured distances scatter.

In the graph the step is an edge between the two clouds' nodes whose information covers
only what the camera sees: the foot's two coordinates and the heading (Jᵀ Σ⁻¹ J with J
the measurement's Jacobian, so a tilt, which moves the foot by Z·θ, is tied to the
translation as the image ties them); height, roll and pitch stay the ToF's. The edge's
transformation is the current estimate moved just enough to agree with the measurement;
both are carried into the ToF's frame by the camera's mounting (``T_tof_camera``). The
same steps, taken along the surface, are the clouds' initial poses
(:meth:`CameraFactors.guided`), so each cloud's ICP starts within millimetres.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from processing.poses import (
    compose_se2,
    relative_se2,
    se3_adjoint_inverse,
    se3_exp,
    wrap_angle,
)


@dataclass(frozen=True)
class CameraModel:
    """A pinhole camera (px) and its pose in the ToF sensor's frame (4, 4, metres)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    T_tof_camera: NDArray[np.float64]

    @classmethod
    def of(cls, spec: Mapping[str, Any]) -> CameraModel:
        """The model of a ``camera.json`` (its intrinsics and ``T_tof_camera``)."""
        return cls(
            int(spec["width"]),
            int(spec["height"]),
            float(spec["fx"]),
            float(spec["fy"]),
            float(spec["cx"]),
            float(spec["cy"]),
            np.asarray(spec["T_tof_camera"], np.float64),
        )


@dataclass(frozen=True)
class CameraParams:
    """The camera factors' error model and which plane is the surface under the camera."""

    sigma_px: float = 0.3  # a frame pair's registration error per axis (px)
    # relative error of the distance that turns px into metres, at least (the route's own
    # scatter of measured distances when larger: :func:`scale_error`)
    sigma_scale: float = 0.005
    # a cloud's plane is the surface under the camera when its normal is this close to the
    # optical axis (cosine)
    min_normal_cos: float = 0.85
    min_plane_points: int = 200
    plane_threshold_m: float = 0.015  # a plane's inliers: within this (about the ToF's noise)
    # the surface is measured this near the camera: farther off a plate ends, steps or
    # bends, and a far point's lever tilts the plane under the camera
    near_m: float = 1.0
    max_points: int = 5000  # of a cloud, for its planes
    # a camera on a wheeled robot stays within this fraction of its usual height
    max_height_change: float = 0.06


@dataclass(frozen=True)
class FootStep:
    """The footprint frame's planar motion (x, y metres, ψ radians) in the earlier frame,
    with its covariance (3, 3)."""

    delta: NDArray[np.float64]
    cov: NDArray[np.float64]


def foot(
    T_ab: NDArray[np.floating], distance_m: float | NDArray[np.floating]
) -> NDArray[np.float64]:
    """(x, y, ψ): where camera b's optical axis meets the surface (the plane z =
    ``distance_m`` of camera a's frame) in camera a's frame, and b's heading there.
    ``T_ab`` (..., 4, 4) and ``distance_m`` (...) give (..., 3)."""
    T = np.asarray(T_ab, np.float64)
    d = T[..., :3, 2]
    s = (distance_m - T[..., 2, 3]) / d[..., 2]
    return np.stack(
        [
            T[..., 0, 3] + s * d[..., 0],
            T[..., 1, 3] + s * d[..., 1],
            np.arctan2(T[..., 1, 0], T[..., 0, 0]),
        ],
        axis=-1,
    )


def _foot_jacobian(T_ab: NDArray[np.float64], distance_m: float) -> NDArray[np.float64]:
    """(3, 6) derivative of :func:`foot` at ``T_ab`` exp(ζ) for ζ = (ω, v) at 0."""
    J = np.zeros((3, 6))
    m0, h = foot(T_ab, distance_m), 1e-6
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = h
        dm = foot(T_ab @ se3_exp(xi), distance_m) - m0
        dm[2] = float(wrap_angle(dm[2]))
        J[:, k] = dm / h
    return J


def camera_edge(
    step: FootStep,
    predicted_tof: NDArray[np.floating],
    distance_m: float,
    camera: CameraModel,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The graph edge of a cloud pair's footprint ``step``: T_a_b in the ToF frame (the
    ``predicted_tof`` relative pose moved to agree with the step) and its information
    (6, 6; rotation first) in the pose graph's convention (error ζ with T = X exp(ζ))."""
    T_tc = np.asarray(camera.T_tof_camera, np.float64)
    X = np.linalg.inv(T_tc) @ np.asarray(predicted_tof, np.float64) @ T_tc  # camera frame
    for _ in range(3):  # Gauss-Newton, moving only what the measurement sees
        r = step.delta - foot(X, distance_m)
        r[2] = float(wrap_angle(r[2]))
        X = X @ se3_exp(np.linalg.pinv(_foot_jacobian(X, distance_m)) @ r)
    J = _foot_jacobian(X, distance_m)
    info_camera = J.T @ np.linalg.inv(step.cov) @ J
    A = se3_adjoint_inverse(T_tc)  # ζ_camera = Ad(T_tc⁻¹) ζ_tof
    info_tof = A.T @ info_camera @ A
    return T_tc @ X @ np.linalg.inv(T_tc), 0.5 * (info_tof + info_tof.T)


def foot_steps_px_to_m(
    deltas_px: Sequence[NDArray[np.floating] | None],
    distances_m: NDArray[np.floating],
    camera: CameraModel,
    params: CameraParams = CameraParams(),
) -> list[FootStep | None]:
    """Each frame pair's registration (dx, dy px, dθ; None where it failed) as a footprint
    step in metres, scaled by the distance to the surface at the earlier frame; its
    covariance is the registration's (the scale's error, common to a stretch of steps, is
    added to the clouds' steps: :func:`with_scale_error`)."""
    out: list[FootStep | None] = []
    for delta, z in zip(deltas_px, distances_m):
        if delta is None or not np.isfinite(z):
            out.append(None)
            continue
        d = np.array([delta[0] * z / camera.fx, delta[1] * z / camera.fy, delta[2]], np.float64)
        sigma_t = params.sigma_px * z / min(camera.fx, camera.fy)
        var_t = sigma_t**2
        sigma_r = params.sigma_px / (0.5 * min(camera.width, camera.height))
        out.append(FootStep(d, np.diag([var_t, var_t, sigma_r**2])))
    return out


def cloud_steps(
    frame_times: NDArray[np.floating],
    steps: Sequence[FootStep | None],
    cloud_times: NDArray[np.floating],
) -> list[FootStep | None]:
    """Footprint steps between consecutive clouds (N - 1; None where the frames do not
    link them): the frames' steps (``steps[k]`` from frame k to k + 1) chained, the ends
    interpolated within a step to the clouds' times."""
    times = np.asarray(frame_times, np.float64)
    # chains of linked frames: F in each chain's first frame's footprint frame, with the
    # variance accumulated from that frame
    segment = np.zeros(len(times), int)
    feet = np.zeros((len(times), 3))
    var = np.zeros((len(times), 3))
    for k, step in enumerate(steps[: len(times) - 1]):
        if step is None:
            segment[k + 1] = segment[k] + 1
            continue
        segment[k + 1] = segment[k]
        feet[k + 1] = compose_se2(feet[k], step.delta)
        var[k + 1] = var[k] + np.diag(step.cov)

    def at(t: float) -> tuple[int, NDArray[np.float64], NDArray[np.float64]] | None:
        k = int(np.searchsorted(times, t, side="right")) - 1
        if k < 0 or t > times[-1]:
            return None
        if k == len(times) - 1 or t == times[k]:
            return int(segment[k]), feet[k], var[k]
        if segment[k + 1] != segment[k]:
            return None
        a = (t - times[k]) / (times[k + 1] - times[k])
        step = relative_se2(feet[k], feet[k + 1])
        return int(segment[k]), compose_se2(feet[k], a * step), var[k] + a * (var[k + 1] - var[k])

    out: list[FootStep | None] = []
    ends = [at(float(t)) for t in cloud_times]
    for a, b in zip(ends[:-1], ends[1:]):
        if a is None or b is None or a[0] != b[0]:
            out.append(None)
            continue
        delta = relative_se2(a[1], b[1])
        v = np.abs(b[2] - a[2])
        # a heading error carried along the step moves its end sideways
        v_t = max(v[0], v[1]) + v[2] * float(delta[0] ** 2 + delta[1] ** 2)
        out.append(FootStep(delta, np.diag([max(v_t, 1e-12), max(v_t, 1e-12), max(v[2], 1e-12)])))
    return out


def scale_error(found_m: NDArray[np.floating], params: CameraParams = CameraParams()) -> float:
    """The relative error of the pixels' scale on a route: the robust scatter (1.4826 MAD)
    of the surface distances its clouds measured (``found_m`` (N,), NaN where none),
    relative to their median, at least ``params.sigma_scale``. A camera on a wheeled robot
    keeps its height over the plate it drives on; where the measured distances scatter, the
    ToF did not see the surface under the camera or the camera sees a plate on the plate,
    and a step's length is that uncertain."""
    found = np.asarray(found_m, np.float64)
    found = found[np.isfinite(found)]
    if len(found) < 2:
        return params.sigma_scale
    median = float(np.median(found))
    scatter = 1.4826 * float(np.median(np.abs(found - median))) / median
    return max(params.sigma_scale, scatter)


def with_scale_error(step: FootStep | None, sigma_scale: float) -> FootStep | None:
    """``step`` with the pixels' relative scale error ``sigma_scale`` added to its
    covariance: it moves the step's end along the step (σ² Δ Δᵀ), not across it, and leaves
    the heading alone."""
    if step is None:
        return None
    cov = step.cov.copy()
    cov[:2, :2] += sigma_scale**2 * np.outer(step.delta[:2], step.delta[:2])
    return FootStep(step.delta, cov)


def along_surface(
    delta: NDArray[np.floating], T_tof_camera: NDArray[np.floating]
) -> NDArray[np.float64]:
    """The ToF's motion (4, 4) of a footprint step ``delta`` (x, y, ψ) taken along the
    surface: no change of the camera's height or tilt."""
    x, y, yaw = (float(v) for v in delta)
    along = np.eye(4)  # the step in the camera's frame, on the surface
    along[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    along[:2, 3] = x, y
    T_tc = np.asarray(T_tof_camera, np.float64)
    return np.asarray(T_tc @ along @ np.linalg.inv(T_tc), np.float64)


@dataclass(frozen=True)
class CameraFactors:
    """What the camera adds to a map: its model, the footprint step between each pair of
    consecutive clouds (N - 1; None where the frames do not link them), the distance
    to the surface at each cloud (N; NaN where unknown) and the relative error of the
    pixels' scale taken for the steps (:func:`scale_error`)."""

    camera: CameraModel
    steps: list[FootStep | None]
    distances_m: NDArray[np.float64]
    scale_sigma: float = CameraParams.sigma_scale

    def guided(self, odometry: NDArray[np.float64] | None, n: int) -> NDArray[np.float64]:
        """(N, 4, 4) initial poses: where the camera links two clouds, its step along the
        surface (the robot stays on it: no change of height or tilt, which the ToF then
        measures), else the odometry's step (identity without odometry); chained from the
        odometry's first pose. ICP then starts within millimetres of the truth in the
        directions the camera sees, and the odometry's tilt errors do not accumulate."""
        T_tc = np.asarray(self.camera.T_tof_camera, np.float64)
        start = np.eye(4) if odometry is None else np.asarray(odometry[0], np.float64)
        poses = [start]
        for i in range(1, n):
            predicted = (
                np.eye(4) if odometry is None else np.linalg.inv(odometry[i - 1]) @ odometry[i]
            )
            step = self.steps[i - 1] if i - 1 < len(self.steps) else None
            z = float(self.distances_m[i - 1])
            if step is not None and np.isfinite(z):
                predicted = along_surface(step.delta, T_tc)
            poses.append(poses[-1] @ predicted)
        return np.array(poses)

    def remounted(self, xi: NDArray[np.floating]) -> CameraFactors:
        """The same factors through the mounting ``T_tof_camera`` exp(ξ) (ξ (6,): a twist in
        the camera's frame, :mod:`.camera_mounting`): distances along the moved axis, steps
        rescaled by them (the pixels' scale is the distance)."""
        xi = np.asarray(xi, np.float64)
        distances = self.distances_m - float(xi[5])
        steps: list[FootStep | None] = []
        for step, z, z_new in zip(self.steps, self.distances_m, distances):
            if step is None or not np.isfinite(z):
                steps.append(step)
                continue
            k = np.array([z_new / z, z_new / z, 1.0])
            steps.append(FootStep(step.delta * k, step.cov * np.outer(k, k)))
        mounting = self.camera.T_tof_camera @ se3_exp(xi)
        return CameraFactors(
            replace(self.camera, T_tof_camera=mounting), steps, distances, self.scale_sigma
        )

    def edges(
        self, poses: NDArray[np.float64]
    ) -> list[tuple[int, int, NDArray[np.float64], NDArray[np.float64]]]:
        """(source i, target i - 1, T_target_source, information) of every linked cloud
        pair, moved from the current ``poses`` (N, 4, 4) to agree with its step."""
        out = []
        for i, step in enumerate(self.steps, start=1):
            z = float(self.distances_m[i - 1])
            if step is None or not np.isfinite(z) or i >= len(poses):
                continue
            predicted = np.linalg.inv(poses[i - 1]) @ poses[i]
            X, info = camera_edge(step, predicted, z, self.camera)
            out.append((i, i - 1, X, info))
        return out


def camera_factors(
    frames: Sequence[NDArray[np.uint8]],
    frame_times: NDArray[np.floating],
    clouds: Sequence[NDArray[np.floating]],
    cloud_times: NDArray[np.floating],
    camera: CameraModel,
    params: CameraParams = CameraParams(),
    deltas: Sequence[NDArray[np.float64] | None] | None = None,
) -> tuple[CameraFactors, int]:
    """The camera's factors of a map: grey ``frames`` (H, W) at ``frame_times`` registered
    pair by pair (or their registrations ``deltas`` from
    :func:`~processing.mapping.frame_pairs.frame_deltas`), scaled by
    the surface distance the ``clouds`` (at ``cloud_times``, the same clock) show, chained
    to the clouds' times, as sure of their length as those distances agree
    (:func:`scale_error`); and how many frame pairs registered."""
    from processing.mapping.frame_pairs import frame_deltas
    from processing.mapping.surface_distance import filled_distances, found_distances

    deltas = frame_deltas(frames) if deltas is None else deltas
    found = found_distances(clouds, camera, params)
    distances, sigma = filled_distances(found, params), scale_error(found, params)
    steps: list[FootStep | None] = [None] * (len(clouds) - 1)
    if np.isfinite(distances).any():
        at_frames = np.interp(frame_times, cloud_times, distances)
        chained = cloud_steps(
            frame_times, foot_steps_px_to_m(deltas, at_frames, camera, params), cloud_times
        )
        steps = [with_scale_error(step, sigma) for step in chained]
    registered = sum(d is not None for d in deltas)
    return CameraFactors(camera, steps, distances, sigma), registered
