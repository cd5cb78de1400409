"""Where the surface the robot stands on is, from one ToF cloud.

Every ray of the depth camera that meets the robot's contact plane (z = 0 in the robot
frame: x forward, y right, z into the surface) is evidence about the point where it meets
it: a return at that range says the surface is there; a return from beyond the plane, or
none at all, says it is not (past an edge, a cut-out, a gap between members); a return from
before the plane says something stands in between (a stiffener, a flange) and says nothing
about the surface. The tolerance is the cloud's own range noise (from the second
differences of neighbouring pixels' ranges, which the smooth shapes of steel members leave
untouched; a cloud without pixel order is put back on its pixel grid first), so no number here is tied to one sensor. Rays meeting the plane
at grazing incidence are left out, as depth cameras lose such returns on bare steel.
Pure functions: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

MAD_TO_SIGMA = 1.4826  # the median absolute deviation of a normal sample, in sigmas


@dataclass(frozen=True)
class SurfaceEvidenceParams:
    """How a cloud's rays are read as evidence about the contact plane."""

    max_incidence_deg: float = 75.0  # rays meeting the plane more obliquely: no evidence
    noise_sigmas: float = 4.0  # a return within this many range-noise sigmas is on the plane
    depth_step_m: float = 0.001  # the encoding's depth step: the least tolerance


@dataclass(frozen=True)
class SurfaceEvidence:
    """Points of the contact plane (robot frame, metres) and what the cloud says of each."""

    xy: NDArray[np.float32]  # (N, 2) where each ray meets the plane
    on: NDArray[np.bool_]  # (N,) the surface is there (else: it is not)
    weight: NDArray[np.float32]  # (N,) cos(incidence): head-on rays say more
    tolerance_m: float  # the range tolerance used (from the cloud's own noise)


def pixel_rays(
    width: int, height: int, fx: float, fy: float, cx: float, cy: float
) -> NDArray[np.float64]:
    """Unit ray directions (H*W, 3) of a pinhole depth camera's pixels, sensor frame,
    row-major (as :func:`robot_link.clouds.depth_to_points` orders its points)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def surface_evidence(
    points: NDArray[np.floating],
    T_robot_sensor: NDArray[np.floating],
    rays: NDArray[np.floating] | None = None,
    params: SurfaceEvidenceParams = SurfaceEvidenceParams(),
) -> SurfaceEvidence:
    """What a cloud says of the contact plane.

    ``points`` (H, W, 3) an organised cloud or (N, 3) one without pixel order, sensor
    frame, NaN for pixels without a return; ``rays`` (H*W or N, 3) each point's unit
    direction (an organised cloud's pixel rays, :func:`pixel_rays`), or None, when only the
    returns' own directions are known (then a missing return is no evidence).
    ``T_robot_sensor`` (4, 4) places the sensor on the robot."""
    grid = np.asarray(points, dtype=np.float64)
    P = grid.reshape(-1, 3)
    T = np.asarray(T_robot_sensor, dtype=np.float64)
    R, o = T[:3, :3], T[:3, 3]
    finite: NDArray[np.bool_] = np.asarray(np.isfinite(P).all(axis=1))
    rng = np.where(finite, np.linalg.norm(np.where(finite[:, None], P, 0.0), axis=1), np.nan)
    if rays is None:
        d = np.where(finite[:, None], P, 0.0) / np.where(rng > 0, rng, 1.0)[:, None]
        known = finite & (rng > 0)
    else:
        d = np.asarray(rays, dtype=np.float64).reshape(-1, 3)
        known = np.ones(len(d), bool)
    dw = d @ R.T  # directions in the robot frame
    height = -o[2]  # the sensor's height above the plane (z points into the surface)
    cos_inc = np.clip(dw[:, 2], 0.0, 1.0)  # the plane's normal is +z
    min_cos = np.cos(np.radians(params.max_incidence_deg))
    meets = known & (cos_inc >= min_cos) & (height > 0)
    t_plane = np.where(meets, height / np.where(cos_inc > 0, cos_inc, 1.0), np.nan)
    resid = rng - t_plane  # > 0: beyond the plane; < 0: something in between
    returned = meets & finite
    if grid.ndim == 3:
        sigma = range_noise(rng.reshape(grid.shape[:2]))
    else:
        sigma = _loose_range_noise(P, resid[returned])
    tol = max(params.noise_sigmas * sigma, params.depth_step_m)
    on = returned & (np.abs(resid) <= tol)
    off = meets & (~finite | (resid > tol))
    keep = on | off
    xy = o[:2] + dw[keep, :2] * t_plane[keep, None]
    return SurfaceEvidence(
        xy.astype(np.float32),
        on[keep],
        cos_inc[keep].astype(np.float32),
        float(tol),
    )


def range_noise(ranges: NDArray[np.floating]) -> float:
    """The range noise (sigma, metres) of an organised cloud's (H, W) ranges (NaN: none):
    the median absolute second difference along rows, scaled to a sigma (a second
    difference of independent noise has sqrt(6) sigmas; a plane or a smooth member adds
    next to nothing); 0 with under 10 triples of returns."""
    r = np.asarray(ranges, dtype=np.float64)
    d2 = (r[:, :-2] - 2 * r[:, 1:-1] + r[:, 2:]).ravel()
    d2 = d2[np.isfinite(d2)]
    if len(d2) < 10:
        return 0.0
    return MAD_TO_SIGMA * float(np.median(np.abs(d2))) / np.sqrt(6.0)


def _loose_range_noise(points: NDArray[np.float64], resid: NDArray[np.float64]) -> float:
    """The range noise of a cloud without pixel order: from its pixel grid where it can be
    recovered (:func:`processing.mapping.selection.regrid`), else the spread of its returns
    about the plane."""
    from processing.mapping.selection import regrid  # Open3D: only for such clouds

    grid = regrid(points)
    if grid is not None:
        organised, shape = grid
        return range_noise(np.linalg.norm(organised, axis=1).reshape(shape))
    return _spread_about_plane(resid)


def _spread_about_plane(resid: NDArray[np.float64]) -> float:
    """The range noise (sigma, metres) of returns about the plane: the median absolute
    residual (about zero: the plane is where the robot stands), then again over the returns
    within three of those (occluders and far returns trimmed); 0 with under 10 returns.
    Returns off the plane inflate it where they are the most."""
    a = np.abs(resid)
    if len(a) < 10:
        return 0.0
    sigma = MAD_TO_SIGMA * float(np.median(a))
    near = a[a <= 3 * sigma]
    return MAD_TO_SIGMA * float(np.median(near)) if len(near) >= 10 else sigma
