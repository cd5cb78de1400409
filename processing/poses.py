"""All pose algebra: planar poses (SE(2)), rigid transforms (SE(3)), frame-pixel maps, TUM text.

A planar pose is a row (x, y, θ): a position and the angle from the reference frame's x axis
to the pose's x axis (radians, positive from x towards y). 3D poses are 4×4 matrices named
``T_a_b`` (b's frame in a's), composed as ``T_a_c = T_a_b @ T_b_c``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray


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


def rot2(theta: float) -> NDArray[np.float64]:
    """2×2 rotation by ``theta`` radians."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def compose_se2(a: NDArray[np.floating], b: NDArray[np.floating]) -> NDArray[np.float64]:
    """Compose planar poses given as (x, y, θ) rows: a ∘ b, the pose b given in a's frame
    placed in a's reference frame (inverse of :func:`relative_se2`)."""
    t = np.asarray(a[:2], float) + rot2(float(a[2])) @ np.asarray(b[:2], float)
    yaw = float(a[2]) + float(b[2])
    return np.array([t[0], t[1], np.arctan2(np.sin(yaw), np.cos(yaw))])  # in (-π, π]


def relative_se2(a: NDArray[np.floating], b: NDArray[np.floating]) -> NDArray[np.float64]:
    """Pose b in pose a's frame: (R_aᵀ (t_b − t_a), θ_b − θ_a)."""
    d = rot2(float(a[2])).T @ (np.asarray(b[:2], float) - np.asarray(a[:2], float))
    return np.array([d[0], d[1], float(wrap_angle(b[2] - a[2]))])


def half_se2(step: NDArray[np.floating]) -> NDArray[np.float64]:
    """The planar step h (x, y, θ) that taken twice is ``step``: h ∘ h = step, turning by
    θ / 2 and moving by (I + R(θ / 2))⁻¹ t."""
    half = float(wrap_angle(step[2])) / 2
    t = np.linalg.solve(np.eye(2) + rot2(half), np.asarray(step[:2], float))
    return np.array([t[0], t[1], half])


def wheel_speeds(v: float, w: float, track_m: float) -> tuple[float, float]:
    """Left and right wheel speeds (m/s) of a differential drive moving at ``v`` (m/s) and
    turning at ``w`` (rad/s) about its z axis, which points into the surface (x forward, y
    to its right): turning right (w > 0) the left wheels run faster."""
    half = track_m / 2
    return v + w * half, v - w * half


def wheel_turn(left: float, right: float, track_m: float) -> float:
    """The turn (rad, about z into the surface) of a differential drive whose left and right
    wheels moved ``left`` and ``right`` (m): inverse of :func:`wheel_speeds`."""
    return (left - right) / track_m


def integrate_arc(pose: NDArray[np.floating], d: float, dth: float) -> NDArray[np.float64]:
    """Pose (x, y, θ) after a planar move of ``d`` metres while turning ``dth`` radians
    (midpoint integration, as a wheel odometer steps)."""
    x, y, th = (float(v) for v in pose)
    mid = th + dth / 2
    return np.array([x + d * np.cos(mid), y + d * np.sin(mid), float(wrap_angle(th + dth))])


def se2_of_matrix(M: NDArray[np.floating]) -> NDArray[np.float64]:
    """(x, y, θ) of a 3×3 planar (or 4×4, rotated about z) homogeneous matrix."""
    n = M.shape[0] - 1
    return np.array([M[0, n], M[1, n], np.arctan2(M[1, 0], M[0, 0])])


def chain_se2(
    first: NDArray[np.floating], steps: Sequence[NDArray[np.floating]]
) -> NDArray[np.float64]:
    """Poses (N+1, 3) from a first pose and the relative step to each next one."""
    out = [np.asarray(first, float)]
    for d in steps:
        out.append(compose_se2(out[-1], d))
    return np.array(out)


def frame_to_mosaic(pose: NDArray[np.floating], size: tuple[int, int]) -> NDArray[np.float64]:
    """3×3 map from the pixels of a frame of ``size`` (w, h) centred at ``pose`` to mosaic pixels."""
    w, h = size
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    R = rot2(float(pose[2]))
    return np.vstack([np.hstack([R, (np.asarray(pose[:2], float) - R @ c)[:, None]]), [0, 0, 1.0]])


def frame_i_to_j(delta: NDArray[np.floating], size: tuple[int, int]) -> NDArray[np.float64]:
    """3×3 map from frame-i pixels to frame-j pixels for j's relative pose ``delta``."""
    w, h = size
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    Rt = rot2(float(delta[2])).T
    return np.vstack(
        [np.hstack([Rt, (c - Rt @ (c + np.asarray(delta[:2], float)))[:, None]]), [0, 0, 1.0]]
    )


def delta_of_map(M: NDArray[np.float64], size: tuple[int, int]) -> NDArray[np.float64]:
    """Inverse of :func:`frame_i_to_j`: the relative pose of a frame-i → frame-j map."""
    w, h = size
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    phi = -np.arctan2(M[1, 0], M[0, 0])
    d = rot2(phi) @ (c - M[:2, 2]) - c
    return np.array([d[0], d[1], phi])


def format_tum(timestamps: NDArray[np.floating], poses: NDArray[np.floating]) -> str:
    """TUM text (``t tx ty tz qx qy qz qw`` per line) of (N,) times and (N, 4, 4) poses."""
    if len(timestamps) != len(poses):
        raise ValueError(
            f"timestamps ({len(timestamps)}) and poses ({len(poses)}) differ in length"
        )
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    from scipy.spatial.transform import Rotation

    for t, T in zip(timestamps, poses):
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
        tx, ty, tz = T[:3, 3]
        lines.append(
            f"{t:.6f} {tx:.6f} {ty:.6f} {tz:.6f} {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}"
        )
    return "\n".join(lines) + "\n"


def tum_rows(text: str) -> NDArray[np.float64]:
    """(N, 8) rows ``t tx ty tz q1 q2 q3 q4`` of TUM text, checked: eight finite numbers a
    line and a quaternion of non-zero length; a ValueError names the first bad line."""
    rows = []
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 8:
            raise ValueError(f"TUM line {lineno}: expected 8 numbers, got {len(parts)}")
        try:
            row = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"TUM line {lineno}: not a number") from None
        if not np.isfinite(row).all():
            raise ValueError(f"TUM line {lineno}: NaN or infinite value")
        if np.linalg.norm(row[4:]) < 1e-9:
            raise ValueError(f"TUM line {lineno}: quaternion has zero length")
        rows.append(row)
    return np.array(rows, np.float64).reshape(-1, 8)


def quaternion_matrices(q: NDArray[np.floating]) -> NDArray[np.float64]:
    """(N, 3, 3) rotation matrices of (N, 4) quaternions ``x y z w`` (normalised here)."""
    q = np.asarray(q, np.float64)
    x, y, z, w = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def poses_of_tum_rows(rows: NDArray[np.floating], *, w_first: bool = False) -> NDArray[np.float64]:
    """(N, 4, 4) poses of (N, 8) TUM rows (:func:`tum_rows`); ``w_first`` reads each
    quaternion as ``qw qx qy qz`` (a file written in that order) instead of TUM's
    ``qx qy qz qw``."""
    rows = np.asarray(rows, np.float64)
    q = rows[:, 4:]
    if w_first:
        q = np.roll(q, -1, axis=1)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = quaternion_matrices(q)
    poses[:, :3, 3] = rows[:, 1:4]
    return poses


def parse_tum(text: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Parse TUM text into (N,) timestamps and (N, 4, 4) poses; raise ValueError on bad lines."""
    rows = tum_rows(text)
    return rows[:, 0].copy(), poses_of_tum_rows(rows)


def yaw_of(T: NDArray[np.floating]) -> float:
    """Rotation about z of a 4x4 pose, in radians."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def image_to_world(
    uv: NDArray[np.floating],
    camera_pose: NDArray[np.floating],
    px_per_m: float,
    size: tuple[int, int],
) -> NDArray[np.float64]:
    """World (x, y) of downward-camera pixels: the chain image → camera → world (paper §3.1).

    ``uv`` is (N, 2) pixel coordinates, ``camera_pose`` the camera centre (x, y, yaw) on
    the surface, ``size`` the image (width, height); image x lies along the camera's yaw.
    """
    w, h = size
    c, s = np.cos(camera_pose[2]), np.sin(camera_pose[2])
    offset = (np.asarray(uv, dtype=np.float64) - ((w - 1) / 2, (h - 1) / 2)) / px_per_m
    return offset @ np.array([[c, s], [-s, c]]) + camera_pose[:2]


def world_box(
    bbox: tuple[int, int, int, int],
    camera_pose: NDArray[np.floating],
    px_per_m: float,
    size: tuple[int, int],
) -> tuple[float, float, float, float]:
    """World (x, y, w, h) in metres of the axis-aligned box around a pixel box (x, y, w, h) of
    a downward-camera image of ``size`` (w, h) taken at ``camera_pose``."""
    x, y, w, h = bbox
    corners = image_to_world(
        np.array([[x, y], [x + w, y], [x, y + h], [x + w, y + h]]), camera_pose, px_per_m, size
    )
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    return float(lo[0]), float(lo[1]), float(hi[0] - lo[0]), float(hi[1] - lo[1])


def skew(v: NDArray[np.floating]) -> NDArray[np.float64]:
    """The cross-product matrix [v]× (3, 3) of a 3-vector: [v]× w = v × w."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], np.float64)


def se3_adjoint_inverse(T: NDArray[np.floating]) -> NDArray[np.float64]:
    """Ad(T⁻¹) (6, 6) for (ω, v) motions: a world-frame perturbation of T in T's own frame."""
    R, t = np.asarray(T[:3, :3], np.float64), np.asarray(T[:3, 3], np.float64)
    out = np.zeros((6, 6))
    out[:3, :3] = out[3:, 3:] = R.T
    out[3:, :3] = -R.T @ skew(t)
    return out


def se3_exp(xi: NDArray[np.floating]) -> NDArray[np.float64]:
    """4x4 transform of a small motion xi = (ω, v) (rotation vector, translation), as used
    for a right perturbation T · exp(xi) (rotation and translation apart: exact for the
    rotation, first order for the coupling, which the iterations absorb)."""
    T = np.eye(4)
    w = np.asarray(xi[:3], dtype=np.float64)
    theta = float(np.sqrt(w @ w))
    K = skew(w)
    if theta < 1e-8:  # Rodrigues' formula to first order
        T[:3, :3] += K
    else:
        T[:3, :3] += np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta**2 * (K @ K)
    T[:3, 3] = xi[3:]
    return T


def se3_log(T: NDArray[np.floating]) -> NDArray[np.float64]:
    """(ω, v) of a 4x4 transform: rotation vector and translation (the inverse of :func:`se3_exp`)."""
    R = np.asarray(T[:3, :3], dtype=np.float64)
    cos = float(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))
    if cos < -0.99:  # near a half turn the axis is not in R - Rᵀ: the general solver
        from scipy.spatial.transform import Rotation

        w = Rotation.from_matrix(R).as_rotvec()
    else:
        vee = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2
        theta = float(np.arccos(cos))
        w = vee if theta < 1e-8 else vee * (theta / np.sin(theta))
    return np.concatenate([w, np.asarray(T[:3, 3], dtype=np.float64)])


def interpolate_poses(
    times: NDArray[np.floating], poses: NDArray[np.floating], at: NDArray[np.floating]
) -> NDArray[np.float64]:
    """Poses (4, 4) at times ``at`` between the (N, 4, 4) ``poses`` at ``times``: rotation
    slerped, translation linear."""
    from scipy.spatial.transform import Rotation, Slerp

    poses = np.asarray(poses, np.float64)
    at = np.clip(np.asarray(at, np.float64), times[0], times[-1])
    out = np.tile(np.eye(4), (len(at), 1, 1))
    out[:, :3, :3] = Slerp(times, Rotation.from_matrix(poses[:, :3, :3]))(at).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(at, times, poses[:, k, 3])
    return out
