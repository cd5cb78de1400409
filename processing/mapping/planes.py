"""Planes of a steel structure (deck plate, girder web, stiffener faces) as landmarks of the 3D map.

The deck plate and a girder's web are planes metres across that the ToF camera sees from
every pose of a lane, and a transverse stiffener's face is seen for a metre or two of
travel. Consecutive ICP registrations each carry a small heading error and those errors
add up; the angle and distance of a cloud to a plane it shares with much earlier clouds
do not. :func:`extract_planes` finds such planes in one cloud (RANSAC from a fixed seed,
then least-squares refits), :func:`to_frame` moves a plane between frames,
:func:`same_plane` associates them, :func:`plane_frame` gives a landmark its pose-graph
node and :func:`plane_edge` turns one sighting into a pose-graph constraint on the three
directions a plane fixes (two tilts and the distance along its normal), leaving the three
it does not (sliding along it, turning about its normal) to ICP and the odometry. The
plate holds height, roll and pitch; the web heading and the distance across; the
stiffeners' faces the distance along the girder.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from processing.poses import skew


@dataclass(frozen=True)
class Plane:
    """A plane n·x + d = 0 (unit normal towards the sensor) and its inlier points (K, 3)."""

    normal: NDArray[np.float64]
    offset: float
    points: NDArray[np.float64]

    @cached_property
    def centroid(self) -> NDArray[np.float64]:
        """Mean of the inliers."""
        return self.points.mean(axis=0)

    @cached_property
    def second_moment(self) -> NDArray[np.float64]:
        """Σ p pᵀ over the inliers (3x3)."""
        return self.points.T @ self.points

    @property
    def extent(self) -> tuple[float, float]:
        """Standard deviations of the inliers along the plane's two principal directions (m)."""
        centred = self.points - self.centroid
        s = np.sqrt(np.clip(np.linalg.eigvalsh(centred.T @ centred / len(centred)), 0, None))
        return float(s[2]), float(s[1])


def _fit(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """Least-squares plane through points: unit normal (smallest principal axis) and offset."""
    c = points.mean(axis=0)
    normal = np.linalg.eigh((points - c).T @ (points - c))[1][:, 0]
    return normal, float(-normal @ c)


def extract_planes(
    points: NDArray[np.float64],
    normals: NDArray[np.float64] | None = None,
    *,
    max_planes: int = 3,
    min_points: int = 40,
    min_extent_m: tuple[float, float] = (0.035, 0.025),
    distance_m: float = 0.006,
    max_normal_deg: float = 45.0,
    hypotheses: int = 150,
    score_points: int = 250,
    max_split_deg: float = 2.0,
) -> list[Plane]:
    """The largest planes of a cloud (sensor frame), biggest first, normals towards the sensor.

    Repeatedly: RANSAC over the remaining points (``hypotheses`` planes through three of
    them, drawn from a fixed seed: the same cloud gives the same planes), the one with most
    of ~``score_points`` of them within ``distance_m``, refitted by least squares twice;
    with ``normals``, points whose normal is more than ``max_normal_deg`` off do not count
    (a face crossing the plane).
    A plane is kept with ``min_points`` inliers spread at least ``min_extent_m`` (standard
    deviations along its two axes: a stiffener's face is a landmark, a bolt head is not) whose two
    halves (split along its longer axis) fit planes within ``max_split_deg`` of it: a plane
    through a stretch of web and a stiffener's edge metres away, tilted by a few degrees,
    is refused.
    Normals only veto (at a wide angle): on far surfaces seen at a grazing angle the ToF's
    samples are centimetres apart and their estimated normals too rough to cluster by.
    """
    points = np.asarray(points, dtype=np.float64)
    cos_max = np.cos(np.radians(max_normal_deg))
    rng = np.random.default_rng(0)
    remaining = np.arange(len(points))
    planes: list[Plane] = []
    # a plane refused for its shape is removed too: a few more tries
    for _ in range(max_planes * 2):
        if len(planes) == max_planes or len(remaining) < max(min_points, 3):
            break
        pts = points[remaining]
        own = None if normals is None else np.asarray(normals)[remaining]
        found = _ransac(pts, own, rng, hypotheses, score_points, distance_m, cos_max)
        if found is None:
            break
        normal, offset, inliers = found
        taken = remaining[inliers]
        remaining = remaining[~inliers]
        if len(taken) < min_points:  # the best of the rest is too small: nothing bigger is left
            break
        if normal @ points[taken].mean(axis=0) > 0:  # towards the sensor at the origin
            normal, offset = -normal, -offset
        plane = Plane(normal, float(offset), points[taken])
        major, minor = plane.extent
        if (
            major >= min_extent_m[0]
            and minor >= min_extent_m[1]
            and _halves_agree(plane, max_split_deg)
        ):
            planes.append(plane)
    return planes


def _ransac(
    pts: NDArray[np.float64],
    own: NDArray[np.float64] | None,
    rng: np.random.Generator,
    hypotheses: int,
    score_points: int,
    distance_m: float,
    cos_max: float,
) -> tuple[NDArray[np.float64], float, NDArray[np.bool_]] | None:
    """The plane with most support among ``hypotheses`` through three of ``pts`` (scored
    on ~``score_points`` of them), refitted by least squares twice: its unit normal,
    offset and inliers; None when no three points span a plane."""
    a, b, c = (pts[rng.integers(0, len(pts), hypotheses)] for _ in range(3))
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    good = norm > 1e-9
    n, a = n[good] / norm[good, None], a[good]
    if not len(n):
        return None
    stride = max(1, len(pts) // score_points)
    scores = _support(
        pts[::stride], None if own is None else own[::stride], n, a, distance_m, cos_max
    ).sum(axis=0)
    best = int(np.argmax(scores))
    normal = n[best]
    inliers = _support(pts, own, n[best : best + 1], a[best : best + 1], distance_m, cos_max)[:, 0]
    offset = 0.0
    for _ in range(2):
        if inliers.sum() < 3:
            break
        normal, offset = _fit(pts[inliers])
        inliers = _support(pts, own, normal[None], -offset * normal[None], distance_m, cos_max)[
            :, 0
        ]
    return normal, offset, inliers


def _support(
    points: NDArray[np.float64],
    normals: NDArray[np.float64] | None,
    n: NDArray[np.float64],
    a: NDArray[np.float64],
    distance_m: float,
    cos_max: float,
) -> NDArray[np.bool_]:
    """(K, H): whether each point lies within ``distance_m`` of each plane (normal n through
    a), with its own normal within the angle whose cosine is ``cos_max``, when given."""
    close = np.abs(points @ n.T - np.einsum("ij,ij->i", n, a)) < distance_m
    if normals is not None:
        close &= np.abs(normals @ n.T) > cos_max
    return close


def _halves_agree(plane: Plane, max_deg: float) -> bool:
    """Whether least-squares planes through each half of the inliers (split at the median
    along the longer axis) are within ``max_deg`` of the whole one."""
    centred = plane.points - plane.centroid
    along = centred @ np.linalg.eigh(centred.T @ centred)[1][:, -1]
    cos_max = np.cos(np.radians(max_deg))
    for half in (along <= np.median(along), along > np.median(along)):
        if half.sum() < 3 or abs(_fit(plane.points[half])[0] @ plane.normal) < cos_max:
            return False
    return True


def to_frame(plane: Plane, T: NDArray[np.float64]) -> Plane:
    """The plane in another frame, ``T`` mapping its frame into that one."""
    R, t = T[:3, :3], T[:3, 3]
    normal = R @ plane.normal
    return Plane(normal, float(plane.offset - normal @ t), plane.points @ R.T + t)


def plane_frame(plane: Plane) -> NDArray[np.float64]:
    """A frame on the plane: origin at its inliers' centroid, z along its normal."""
    z = plane.normal / np.linalg.norm(plane.normal)
    x = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    c = plane.centroid
    T[:3, 3] = c - (z @ c + plane.offset) * z
    return T


def same_plane(a: Plane, b: Plane, max_angle_deg: float, max_offset_m: float) -> bool:
    """Whether two planes in one frame are the same: normals within ``max_angle_deg`` and
    each one's inlier centroid within ``max_offset_m`` of the other plane."""
    if a.normal @ b.normal < np.cos(np.radians(max_angle_deg)):
        return False
    return bool(
        abs(b.normal @ a.centroid + b.offset) < max_offset_m
        and abs(a.normal @ b.centroid + a.offset) < max_offset_m
    )


def plane_edge(
    source: Plane, target: Plane, T_target_source: NDArray[np.float64], sigma_m: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A pose-graph edge saying that ``source`` (seen in the source cloud) is ``target``
    (seen in the target cloud), from the current estimate ``T_target_source``: the estimate
    corrected as little as possible so the planes coincide, and its information (Open3D's
    order, rotation then translation, in the source frame where Open3D measures an edge's
    error) as for point-to-plane residuals of the source's inliers against the target
    plane, σ = ``sigma_m``: rank 3, nothing along the plane or about its normal."""
    normal = T_target_source[:3, :3] @ source.normal
    axis = np.cross(normal, target.normal)
    s, c = np.linalg.norm(axis), float(normal @ target.normal)
    correction = np.eye(4)
    centre = T_target_source[:3, :3] @ source.centroid + T_target_source[:3, 3]
    if s > 1e-12:  # rotate the source's plane onto the target's, about its inliers' centre
        K = skew(axis / s)
        R = np.eye(3) + s * K + (1 - c) * K @ K  # Rodrigues
        correction[:3, :3] = R
        correction[:3, 3] = centre - R @ centre
    gap = target.normal @ (correction[:3, :3] @ centre + correction[:3, 3]) + target.offset
    correction[:3, 3] -= gap * target.normal
    measurement = correction @ T_target_source
    # J = [q × n, n] per inlier q (source frame, where Open3D measures an edge's error) and
    # the target's normal n in that frame; q × n = Mᵀ q, so Σ JᵀJ needs only Σ q and Σ q qᵀ
    n = measurement[:3, :3].T @ target.normal
    M = skew(n)
    count = len(source.points)
    info = np.empty((6, 6))
    info[:3, :3] = M.T @ source.second_moment @ M
    info[:3, 3:] = np.outer(M.T @ (count * source.centroid), n)
    info[3:, :3] = info[:3, 3:].T
    info[3:, 3:] = count * np.outer(n, n)
    return measurement, info / sigma_m**2
