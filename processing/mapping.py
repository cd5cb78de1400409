"""3D map of the structure from ToF clouds by ICP (paper §3.2).

First version: selection by voxel downsampling, matching seeded by odometry, point-to-
plane alignment against a local map of recent clouds, with the paper's stopping rules
as Open3D's convergence criteria. Falls back to odometry where ICP finds too little.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class IcpParams:
    """Options of the map builder (lengths in metres)."""

    voxel_m: float = 0.02
    max_correspondence_m: float = 0.06
    max_iterations: int = 40
    relative_fitness: float = 1e-6
    relative_rmse: float = 1e-6
    min_fitness: float = 0.3
    local_map_clouds: int = 8
    map_voxel_m: float = 0.01
    max_range_m: float = 4.0
    degenerate_ratio: float = 0.25
    max_correction_m: float = 0.10
    max_correction_deg: float = 10.0


@dataclass
class MapResult:
    """Registered poses T_world_sensor (N, 4, 4), the fused map (M, 3) and per-cloud facts."""

    poses: NDArray[np.float64]
    points: NDArray[np.float32]
    fitness: NDArray[np.float64]
    rmse: NDArray[np.float64]
    used_odometry: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    degenerate_dims: NDArray[np.int_] = field(default_factory=lambda: np.zeros(0, int))


def clean_cloud(points: NDArray[np.floating], max_range_m: float) -> NDArray[np.float64]:
    """Drop NaN/inf points and returns beyond ``max_range_m``; returns (K, 3) float64."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ok = np.isfinite(pts).all(axis=1)
    pts = pts[ok]
    return pts[np.linalg.norm(pts, axis=1) <= max_range_m]


def preprocess(points: NDArray[np.floating], params: IcpParams) -> o3d.geometry.PointCloud:
    """Selection step: clean, voxel-downsample and estimate normals."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(clean_cloud(points, params.max_range_m)))
    pcd = pcd.voxel_down_sample(params.voxel_m)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=params.voxel_m * 3, max_nn=30))
    pcd.orient_normals_towards_camera_location(np.zeros(3))
    return pcd


def register_clouds(
    clouds: Sequence[NDArray[np.floating]],
    initial_poses: NDArray[np.floating] | None = None,
    *,
    params: IcpParams = IcpParams(),
) -> MapResult:
    """Register clouds (each (K, 3), sensor frame) into one world map.

    Parameters
    ----------
    clouds : sequence of (K, 3) arrays; NaN rows are ignored.
    initial_poses : (N, 4, 4) odometry guesses of T_world_sensor, or None (the first cloud
        is the world frame and motion is estimated from geometry alone).

    Returns
    -------
    MapResult
    """
    n = len(clouds)
    if n == 0:
        raise ValueError("clouds must not be empty")
    if initial_poses is not None:
        initial_poses = np.asarray(initial_poses, dtype=np.float64)
        if initial_poses.shape != (n, 4, 4):
            raise ValueError(f"initial_poses must be ({n}, 4, 4), got {initial_poses.shape}")
    guess = initial_poses if initial_poses is not None else np.repeat(np.eye(4)[None], n, axis=0)
    poses = np.zeros((n, 4, 4))
    fitness, rmse = np.zeros(n), np.zeros(n)
    used_odo = np.zeros(n, bool)
    degenerate = np.zeros(n, int)
    pcds = [preprocess(c, params) for c in clouds]
    poses[0] = guess[0]
    fitness[0] = 1.0
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(
        relative_fitness=params.relative_fitness,
        relative_rmse=params.relative_rmse,
        max_iteration=params.max_iterations,
    )
    estimator = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    for i in range(1, n):
        # odometry increment applied to the last estimate (or the last motion without odometry)
        if initial_poses is not None:
            delta = np.linalg.inv(guess[i - 1]) @ guess[i]
        else:
            delta = np.linalg.inv(poses[i - 2]) @ poses[i - 1] if i >= 2 else np.eye(4)
        init = poses[i - 1] @ delta
        target = _local_map(pcds, poses, i, params)
        if len(pcds[i].points) < 10 or len(target.points) < 10:
            poses[i], used_odo[i] = init, True
            continue
        reg = o3d.pipelines.registration.registration_icp(
            pcds[i], target, params.max_correspondence_m, init, estimator, criteria
        )
        fitness[i], rmse[i] = reg.fitness, reg.inlier_rmse
        if reg.fitness < params.min_fitness or not np.isfinite(reg.transformation).all():
            poses[i], used_odo[i] = init, True
            continue
        poses[i], degenerate[i] = constrain_to_observable(init, reg.transformation, pcds[i], target, params)
        if not _within_bounds(init, poses[i], params):  # paper's stop rule 3: out of bounds
            poses[i], used_odo[i] = init, True
    points = fuse_map(pcds, poses, params.map_voxel_m)
    return MapResult(poses, points, fitness, rmse, used_odo, degenerate)


def _within_bounds(init: NDArray[np.float64], T: NDArray[np.float64], params: IcpParams) -> bool:
    d = np.linalg.inv(init) @ T
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(d[:3, :3]).as_rotvec()))
    return bool(np.linalg.norm(d[:3, 3]) <= params.max_correction_m and angle <= params.max_correction_deg)


def constrain_to_observable(
    init: NDArray[np.float64],
    T_icp: NDArray[np.float64],
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    params: IcpParams,
) -> tuple[NDArray[np.float64], int]:
    """Keep ICP's correction only along directions the geometry constrains.

    The point-to-plane Hessian's translational block (mean of n nᵀ) and rotational block
    (mean of (q-c)×n outer products, scaled by the cloud's spread) are decomposed; along
    eigen-directions weaker than ``degenerate_ratio`` (a flat plate gives no constraint in
    its own plane, nor in rotation about its normal) the odometry's value is kept.
    Returns the pose and the number of degenerate directions (0-6).
    """
    q = np.asarray(source.points) @ T_icp[:3, :3].T + T_icp[:3, 3]
    tgt = np.asarray(target.points)
    dist, idx = cKDTree(tgt).query(q, distance_upper_bound=params.max_correspondence_m)
    ok = np.isfinite(dist)
    if ok.sum() < 10:
        return init, 6
    q, normals = q[ok], np.asarray(target.normals)[idx[ok]]
    c = q.mean(axis=0)
    spread = float(np.mean(np.sum((q - c) ** 2, axis=1))) or 1.0
    cross = np.cross(q - c, normals)
    P_t, dt = _projector(normals.T @ normals / len(q), params.degenerate_ratio)
    P_r, dr = _projector(cross.T @ cross / (len(q) * spread), params.degenerate_ratio)
    dT = T_icp @ np.linalg.inv(init)
    R = dT[:3, :3]
    omega = Rotation.from_matrix(R).as_rotvec()
    tau = dT[:3, 3] + R @ c - c
    R2 = Rotation.from_rotvec(P_r @ omega).as_matrix()
    out = np.eye(4)
    out[:3, :3] = R2
    out[:3, 3] = c - R2 @ c + P_t @ tau
    return out @ init, dt + dr


def _projector(A: NDArray[np.float64], ratio: float) -> tuple[NDArray[np.float64], int]:
    """Projector onto eigen-directions of A whose eigenvalue is at least ``ratio``·trace."""
    evals, evecs = np.linalg.eigh(A)
    good = evals >= ratio * max(float(np.trace(A)), 1e-12)
    V = evecs[:, good]
    return V @ V.T, int((~good).sum())


def _local_map(
    pcds: list[o3d.geometry.PointCloud], poses: NDArray[np.float64], i: int, params: IcpParams
) -> o3d.geometry.PointCloud:
    target = o3d.geometry.PointCloud()
    for j in range(max(0, i - params.local_map_clouds), i):
        target += o3d.geometry.PointCloud(pcds[j]).transform(poses[j])
    target = target.voxel_down_sample(params.voxel_m)
    if not target.has_normals():
        target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=params.voxel_m * 3, max_nn=30))
    return target


def fuse_map(
    pcds: Sequence[o3d.geometry.PointCloud], poses: NDArray[np.float64], voxel_m: float
) -> NDArray[np.float32]:
    """All clouds in the world frame, voxel-filtered, as (M, 3) float32."""
    fused = o3d.geometry.PointCloud()
    for pcd, T in zip(pcds, poses):
        fused += o3d.geometry.PointCloud(pcd).transform(T)
    fused = fused.voxel_down_sample(voxel_m)
    return np.asarray(fused.points, dtype=np.float32)
