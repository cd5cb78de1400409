"""``steelscan bench map``: trajectory error and speed of the 3D map against odometry
alone and Open3D's tutorial registration pipeline."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from server.bench.common import Result


def bench_map(dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Trajectory error (ATE) of the map against the simulator's true ToF poses, and time,
    against Open3D's tutorial pipeline (FPFH + RANSAC global registration, then
    point-to-plane ICP, cloud to cloud) on the same clouds."""
    from processing.mapping import IcpParams, preprocess, register_clouds
    from processing.metrics import absolute_trajectory_error
    from processing.poses import se2_to_se3
    from robot_link.clouds import decode_cloud
    from robot_link.sim.inspection import SimConfig
    from robot_link.sim.recording import record_inspection

    rec = record_inspection(SimConfig(lanes=2, seed=23))
    assert rec.result is not None
    T_rt = np.array(rec.calibration["tof"]["T_robot_tof"])
    clouds, guess, truth = [], [], []
    for m in rec.cloud_messages[:limit]:
        pts = decode_cloud(m.payload, m.meta)
        if not np.isfinite(pts).all(axis=1).any():
            continue
        p = m.meta["pose"]
        clouds.append(pts)
        guess.append(se2_to_se3(p["x"], p["y"], p["yaw"]) @ T_rt)
        truth.append(rec.result.cloud_poses_true[m.seq])
    guess_a, truth_a = np.array(guess), np.array(truth)
    t0 = time.perf_counter()
    ours = register_clouds(clouds, guess_a)
    ours_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    tutorial = _open3d_tutorial_poses([preprocess(c, IcpParams()) for c in clouds], guess_a[0])
    base_s = time.perf_counter() - t0
    ate, ate_base = absolute_trajectory_error(ours.poses, truth_a), absolute_trajectory_error(tutorial, truth_a)
    yield {"name": "map.sim.ate", "value": round(ate, 4), "unit": "m", "baseline": round(ate_base, 4),
           "ratio": round(ate / max(ate_base, 1e-9), 3), "baseline_is": "Open3D tutorial FPFH+RANSAC+ICP",
           "odometry_ate": round(absolute_trajectory_error(guess_a, truth_a), 4), "clouds": len(clouds)}
    yield {"name": "map.sim.seconds_per_cloud", "value": round(ours_s / len(clouds), 4), "unit": "s",
           "baseline": round(base_s / len(clouds), 4), "ratio": round(ours_s / base_s, 3)}


def _open3d_tutorial_poses(pcds: list[Any], T0: NDArray[np.float64]) -> NDArray[np.float64]:
    """Open3D's global-registration tutorial, applied cloud to cloud and chained."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    voxel = 0.02
    feats = [reg.compute_fpfh_feature(p, o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 5, max_nn=100)) for p in pcds]
    poses = [T0]
    for i in range(1, len(pcds)):
        ransac = reg.registration_ransac_based_on_feature_matching(
            pcds[i], pcds[i - 1], feats[i], feats[i - 1], True, voxel * 1.5,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(voxel * 1.5)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
        icp = reg.registration_icp(pcds[i], pcds[i - 1], voxel * 0.4 * 3, ransac.transformation,
                                   reg.TransformationEstimationPointToPlane())
        poses.append(poses[-1] @ icp.transformation)
    return np.array(poses)
