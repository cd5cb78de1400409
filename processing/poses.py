"""Rigid transforms (2D and 3D) and the TUM trajectory text format."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation


def wrap_angle(a: NDArray[np.floating] | float) -> NDArray[np.float64]:
    """Angle(s) wrapped to (-π, π]."""
    return np.asarray((np.asarray(a) + np.pi) % (2 * np.pi) - np.pi, dtype=np.float64)


def se2_matrix(x: float, y: float, yaw: float) -> NDArray[np.float64]:
    """3x3 homogeneous matrix of a planar pose (x, y, yaw in radians)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def se2_to_se3(x: float, y: float, yaw: float, z: float = 0.0) -> NDArray[np.float64]:
    """4x4 matrix of a planar pose rotated about the world z axis."""
    T = np.eye(4)
    T[:2, :2] = se2_matrix(x, y, yaw)[:2, :2]
    T[:3, 3] = (x, y, z)
    return T


def compose_se2(a: NDArray[np.floating], b: NDArray[np.floating]) -> NDArray[np.float64]:
    """Compose planar poses given as (x, y, yaw) rows: a ∘ b."""
    m = se2_matrix(*a) @ se2_matrix(*b)
    return np.array([m[0, 2], m[1, 2], np.arctan2(m[1, 0], m[0, 0])])


def format_tum(timestamps: NDArray[np.floating], poses: NDArray[np.floating]) -> str:
    """TUM text (``t tx ty tz qx qy qz qw`` per line) of (N,) times and (N, 4, 4) poses."""
    if len(timestamps) != len(poses):
        raise ValueError(f"timestamps ({len(timestamps)}) and poses ({len(poses)}) differ in length")
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, T in zip(timestamps, poses):
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
        tx, ty, tz = T[:3, 3]
        lines.append(f"{t:.6f} {tx:.6f} {ty:.6f} {tz:.6f} {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}")
    return "\n".join(lines) + "\n"


def parse_tum(text: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Parse TUM text into (N,) timestamps and (N, 4, 4) poses; raise ValueError on bad lines."""
    times, poses = [], []
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 8:
            raise ValueError(f"TUM line {lineno}: expected 8 numbers, got {len(parts)}")
        try:
            t, tx, ty, tz, qx, qy, qz, qw = (float(p) for p in parts)
        except ValueError:
            raise ValueError(f"TUM line {lineno}: not a number") from None
        norm = np.linalg.norm([qx, qy, qz, qw])
        if not np.isfinite(norm) or norm < 1e-9:
            raise ValueError(f"TUM line {lineno}: quaternion has zero length")
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
        T[:3, 3] = (tx, ty, tz)
        times.append(t)
        poses.append(T)
    return np.array(times), np.array(poses).reshape(-1, 4, 4)


def yaw_of(T: NDArray[np.floating]) -> float:
    """Rotation about z of a 4x4 pose, in radians."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def image_to_world(
    uv: NDArray[np.floating], camera_pose: NDArray[np.floating], px_per_m: float, size: tuple[int, int]
) -> NDArray[np.float64]:
    """World (x, y) of downward-camera pixels: the chain image → camera → world (paper §3.1).

    ``uv`` is (N, 2) pixel coordinates, ``camera_pose`` the camera centre (x, y, yaw) on
    the surface, ``size`` the image (width, height); image x lies along the camera's yaw.
    """
    w, h = size
    c, s = np.cos(camera_pose[2]), np.sin(camera_pose[2])
    offset = (np.asarray(uv, dtype=np.float64) - ((w - 1) / 2, (h - 1) / 2)) / px_per_m
    return offset @ np.array([[c, s], [-s, c]]) + camera_pose[:2]


def _se2_of(M: NDArray[np.floating]) -> NDArray[np.float64]:
    return np.array([M[0, 2], M[1, 2], np.arctan2(M[1, 0], M[0, 0])])


def transfer_correction(
    ref_times: NDArray[np.floating], ref_odometry: NDArray[np.floating], ref_truth: NDArray[np.floating],
    times: NDArray[np.floating], odometry: NDArray[np.floating],
) -> NDArray[np.float64]:
    """Correct odometry poses (N, 3: x, y, yaw) taken at ``times`` by a better estimate known
    at other instants: at each reference k the world-frame correction C_k = T_k · O_k⁻¹
    (better pose times the inverse of the odometry there) is interpolated in time (linearly
    in x, y and unwrapped yaw; held constant beyond the ends) and applied, C(t) · O(t).
    Used to carry the mosaic's camera motion over to the ToF clouds."""
    order = np.argsort(ref_times)
    rt = np.asarray(ref_times, dtype=np.float64)[order]
    corr = np.array([_se2_of(se2_matrix(*ref_truth[k]) @ np.linalg.inv(se2_matrix(*ref_odometry[k]))) for k in order])
    corr[:, 2] = np.unwrap(corr[:, 2])
    out = []
    for t, o in zip(np.asarray(times, dtype=np.float64), np.asarray(odometry, dtype=np.float64)):
        c = np.array([np.interp(t, rt, corr[:, d]) for d in range(3)])
        out.append(_se2_of(se2_matrix(*c) @ se2_matrix(*o)))
    return np.array(out)
