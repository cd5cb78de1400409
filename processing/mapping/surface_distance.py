"""How far the downward camera is from the surface under it, measured by the ToF.

The surface is the plane near the camera, facing it, seen nearest its optical axis; it is
found by RANSAC and refitted along the ToF's rays (its noise lies along them: a fit across
the plane tilts towards oblique rays and misplaces the plane under the camera by
millimetres), then carried into the camera's frame. A cloud that shows no such plane, or
one farther from the others than a wheeled robot's camera moves, takes its neighbours'.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from processing.mapping.camera_motion import CameraModel, CameraParams


def largest_plane(
    pts: NDArray[np.float64], threshold_m: float, iterations: int = 100
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The plane (unit normal n, offset d: n·p + d = 0) with the most of ``pts`` (K, 3)
    within ``threshold_m`` (RANSAC, seeded: the same cloud gives the same plane), refitted
    to its inliers by least squares; and those inliers (K,)."""
    rng = np.random.default_rng(0)
    sample = pts[rng.choice(len(pts), min(len(pts), 2000), replace=False)]
    trios = sample[rng.integers(len(sample), size=(iterations, 3))]
    normals = np.cross(trios[:, 1] - trios[:, 0], trios[:, 2] - trios[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    ok = lengths > 1e-12
    normals, trios = normals[ok] / lengths[ok, None], trios[ok]
    offsets = -np.einsum("ij,ij->i", normals, trios[:, 0])
    counts = (np.abs(sample @ normals.T + offsets) < threshold_m).sum(axis=0)
    best = int(np.argmax(counts))
    inliers = np.abs(pts @ normals[best] + offsets[best]) < threshold_m
    centre = pts[inliers].mean(axis=0)
    n = np.linalg.svd(pts[inliers] - centre, full_matrices=False)[2][2]
    inliers = np.abs((pts - centre) @ n) < threshold_m
    return np.append(n, -float(n @ centre)), inliers


def fit_plane_along_rays(
    pts: NDArray[np.float64], plane: NDArray[np.float64], window_m: float, iterations: int = 6
) -> NDArray[np.float64]:
    """``plane`` (n, d) refitted to a range sensor's points ``pts`` ((K, 3), sensor frame)
    by their errors along their rays (Gauss-Newton): a ToF's noise lies along the ray, so a
    fit across the plane (least squares, SVD) tilts towards oblique rays and misplaces the
    plane millimetres away from the view; points farther than ``window_m`` along the ray
    are left out."""
    r = np.linalg.norm(pts, axis=1)
    u = pts / np.maximum(r, 1e-12)[:, None]
    n, d = plane[:3] / np.linalg.norm(plane[:3]), float(plane[3])
    for _ in range(iterations):
        un = u @ n
        facing = np.abs(un) > 0.05
        predicted = -d / np.where(facing, un, 1.0)  # the range at which each ray meets the plane
        residual = r - predicted
        ok = facing & (np.abs(residual) < window_m)
        if ok.sum() < 3:
            break
        # the window shrinks to three robust deviations of the noise: a parallel surface a
        # flange's thickness away drops out
        window_m = min(window_m, max(3 * 1.4826 * float(np.median(np.abs(residual[ok]))), 1e-3))
        ok = facing & (np.abs(residual) < window_m)
        tangent = np.linalg.svd(n[None])[2][1:]  # two directions across n
        J = np.column_stack([d * (u[ok] @ tangent.T) / un[ok, None] ** 2, -1 / un[ok]])
        step = np.linalg.lstsq(J, residual[ok], rcond=None)[0]
        n = n + tangent.T @ step[:2]
        n /= np.linalg.norm(n)
        d += float(step[2])
    return np.append(n, d)


def surface_distance(
    cloud: NDArray[np.floating], camera: CameraModel, params: CameraParams = CameraParams()
) -> float | None:
    """Distance (m) along the optical axis from the camera to the surface under it: of the
    largest planes of ``cloud`` ((K, 3), ToF frame, NaN rows ignored) near the camera and
    facing it, the one seen nearest the axis, fitted along the ToF's rays and carried into
    the camera's frame; None when the cloud shows no such plane."""
    pts = np.asarray(cloud, np.float64).reshape(-1, 3)
    R, t = camera.T_tof_camera[:3, :3], camera.T_tof_camera[:3, 3]
    with np.errstate(invalid="ignore"):
        near = np.linalg.norm(pts - t, axis=1) < params.near_m  # NaN rows compare False
    pts = pts[near]
    # an evenly spread sample: thousands of returns fix a plane to a fraction of a millimetre
    pts = pts[:: max(1, len(pts) // params.max_points)]
    best: tuple[float, float] | None = None  # (gap to the foot, distance)
    for _ in range(3):  # the largest planes in turn: of those facing the camera, the one
        # whose points come nearest the optical axis' foot (a plate on a plate: a step)
        if len(pts) < params.min_plane_points:
            break
        plane, inliers = largest_plane(pts, params.plane_threshold_m)
        if inliers.sum() < params.min_plane_points:
            break
        plane = fit_plane_along_rays(pts, plane, 2 * params.plane_threshold_m)
        n_camera, d_camera = R.T @ plane[:3], plane[3] + plane[:3] @ t
        if abs(n_camera[2]) >= params.min_normal_cos and -d_camera / n_camera[2] > 0:
            distance = float(-d_camera / n_camera[2])  # the axis (0, 0, s) meets the plane
            seen = (pts[inliers] - t) @ R  # camera frame
            gap = float(np.min(np.linalg.norm(seen - (0.0, 0.0, distance), axis=1)))
            if best is None or gap < best[0]:
                best = (gap, distance)
        pts = pts[~inliers]
    return None if best is None else best[1]


def found_distances(
    clouds: Sequence[NDArray[np.floating]],
    camera: CameraModel,
    params: CameraParams = CameraParams(),
) -> NDArray[np.float64]:
    """(N,) :func:`surface_distance` of every cloud, NaN where it shows no surface."""
    return np.array([surface_distance(c, camera, params) or np.nan for c in clouds], float)


def surface_distances(
    clouds: Sequence[NDArray[np.floating]],
    camera: CameraModel,
    params: CameraParams = CameraParams(),
) -> NDArray[np.float64]:
    """(N,) :func:`surface_distance` of every cloud, where a cloud shows no surface (or one
    farther from the others' median than the robot's suspension lets the camera move)
    interpolated from its neighbours; all NaN when no cloud shows it."""
    return filled_distances(found_distances(clouds, camera, params), params)


def filled_distances(
    found_m: NDArray[np.floating], params: CameraParams = CameraParams()
) -> NDArray[np.float64]:
    """The distances ``found_m`` (N,) where a cloud showed none (NaN) or one farther from
    the others' median than the robot's suspension lets the camera move interpolated from
    its neighbours; all NaN when no cloud shows it."""
    found = np.array(found_m, np.float64)
    if np.isfinite(found).any():
        median = float(np.nanmedian(found))
        with np.errstate(invalid="ignore"):
            found[np.abs(found - median) > params.max_height_change * median] = np.nan
    ok = np.isfinite(found)
    if not ok.any():
        return found
    index = np.arange(len(found))
    return np.interp(index, index[ok], found[ok])
