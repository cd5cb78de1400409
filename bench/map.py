"""``steelscan bench map``: trajectory error and speed of the 3D map against odometry
alone and Open3D's tutorial registration pipeline."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from bench.common import Result

if TYPE_CHECKING:
    from processing.mapping import MapResult
    from robot_link.sim.tof_sweeps import TofSweepConfig


def relative_pose_error(
    est: NDArray[np.float64], truth: NDArray[np.float64]
) -> tuple[float, float]:
    """RMSE of the translational error of consecutive relative motions (m) and the largest
    one (a jump: a catastrophic registration)."""
    errs = [
        np.linalg.norm(
            (
                np.linalg.inv(np.linalg.inv(est[k]) @ est[k + 1])
                @ (np.linalg.inv(truth[k]) @ truth[k + 1])
            )[:3, 3]
        )
        for k in range(len(est) - 1)
    ]
    return float(np.sqrt(np.mean(np.square(errs)))), float(np.max(errs))


def _sweeps() -> list[tuple[str, Any]]:
    """The benchmark routes, on seeds the pipeline was not developed on, along the
    simulated girder (its stiffeners repeat every 0.5 m): two routes of two lanes that
    return to their start (a loop), three lanes 12 cm apart and one lane without a return
    (neighbouring lanes see the girder differently: loop closures between them must be
    refused), three lanes beside a girder that ends with the plate (the ToF then sees bare
    plate and then nothing ahead: the degenerate case), and a loop with three times the
    odometry's errors."""
    from robot_link.sim.tof_sweeps import TofSweepConfig

    three = (0.5, 0.62, 0.74)
    return [
        ("sweep31", TofSweepConfig(seed=31)),
        ("sweep32", TofSweepConfig(seed=32)),
        ("three_lanes33", TofSweepConfig(lanes_y_m=three, revisit=False, seed=33)),
        ("one_lane34", TofSweepConfig(lanes_y_m=(0.6,), revisit=False, seed=34)),
        (
            "three_lanes35_bare_girder",
            TofSweepConfig(lanes_y_m=three, revisit=False, girder_overhang_m=0.0, seed=35),
        ),
        (
            "sweep36_poor_odometry",
            TofSweepConfig(odometry_distance_sigma=0.09, odometry_yaw_sigma_deg=1.8, seed=36),
        ),
    ]


def _ate_result(
    name: str, ate: dict[str, float], ours: MapResult, clouds: int, length: float
) -> Result:
    """The map's absolute trajectory error against Open3D's tutorial pipeline and odometry
    alone's, and what the map did (loop closures, odometry fallbacks, planes)."""
    return {
        "name": f"{name}.ate",
        "value": round(ate["ours"], 4),
        "unit": "m",
        "baseline": round(ate["tutorial"], 4),
        "ratio": round(ate["ours"] / max(ate["tutorial"], 1e-9), 3),
        "baseline_is": "Open3D tutorial FPFH+RANSAC+ICP",
        "odometry": round(ate["odometry"], 4),
        "clouds": clouds,
        "path_m": round(length, 2),
        "loop_closures": ours.loop_closures,
        "odometry_fallbacks": int(ours.used_odometry.sum()),
        "odometry_error_scale": round(ours.odometry_error_scale, 2),
        "plane_landmarks": ours.plane_landmarks,
    }


def _drift_result(
    name: str, ate: dict[str, float], length: float, oracle: float, seen: NDArray[np.bool_]
) -> Result:
    """The map's error as a share of the path (``length``) against odometry alone's, beside
    the ``oracle``'s (:func:`oracle_poses`) and how many clouds see structure."""
    return {
        "name": f"{name}.drift",
        "value": round(100 * ate["ours"] / length, 3),
        "unit": "% of path",
        "target": 0.25,
        "baseline": round(100 * ate["odometry"] / length, 3),
        "ratio": round(ate["ours"] / max(ate["odometry"], 1e-9), 3),
        "baseline_is": "odometry alone",
        "oracle_drift": round(100 * oracle / length, 3),
        "oracle_is": "exact steps between clouds that both see structure off the deck plate, odometry's elsewhere",
        "clouds_seeing_structure": int(seen.sum()),
    }


def _rpe_result(name: str, rpe: dict[str, tuple[float, float]]) -> Result:
    """The map's relative pose error and its largest step error, against odometry alone's
    and beside Open3D's tutorial pipeline's."""
    return {
        "name": f"{name}.rpe",
        "value": round(rpe["ours"][0], 4),
        "unit": "m",
        "max_step_error": round(rpe["ours"][1], 4),
        "max_step_target": 0.02,
        "baseline": round(rpe["odometry"][0], 4),
        "baseline_is": "odometry alone",
        "tutorial": round(rpe["tutorial"][0], 4),
        "tutorial_max_step_error": round(rpe["tutorial"][1], 4),
    }


def _route(label: str, config: TofSweepConfig, limit: int | None) -> Iterator[Result]:
    """Trajectory error (ATE, drift, RPE) and time per cloud of the map of one simulated ToF
    sweep (the first ``limit`` clouds) against odometry alone and Open3D's tutorial pipeline."""
    from processing.mapping import SelectParams, register_clouds, select
    from processing.metrics import absolute_trajectory_error
    from robot_link.sim.tof_sweeps import tof_sweep

    sweep = tof_sweep(config, clouds=limit)
    n = len(sweep.clouds)
    clouds, truth, odo = sweep.clouds[:n], sweep.truth[:n], sweep.odometry[:n]
    length = float(np.sum(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1)))
    shape = (int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"]))
    t0 = time.perf_counter()
    ours = register_clouds(clouds, odo, shape=shape)
    ours_ms = 1000 * (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    tutorial = _open3d_tutorial_poses([select(c, SelectParams()) for c in clouds], odo)
    base_ms = 1000 * (time.perf_counter() - t0) / n
    name = f"map.{label}"
    estimates = (("ours", ours.poses), ("odometry", odo), ("tutorial", tutorial))
    ate = {k: absolute_trajectory_error(p, truth) for k, p in estimates}
    rpe = {k: relative_pose_error(p, truth) for k, p in estimates}
    yield _ate_result(name, ate, ours, n, length)
    seen = sees_structure([select(c, SelectParams(), shape) for c in clouds], truth)
    oracle = absolute_trajectory_error(oracle_poses(truth, odo, seen), truth)
    yield _drift_result(name, ate, length, oracle, seen)
    yield _rpe_result(name, rpe)
    yield {
        "name": f"{name}.ms_per_cloud",
        "value": round(ours_ms, 1),
        "unit": "ms",
        "target": 25.0,
        "baseline": round(base_ms, 1),
        "ratio": round(ours_ms / base_ms, 3),
        "baseline_is": "Open3D tutorial FPFH+RANSAC+ICP",
    }


def bench_map(dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Per structure type (:mod:`bench.map_structures`; with ``limit``, one held-back seed of
    ``limit`` clouds each and the whole command on the first type only), then
    trajectory error (ATE, RPE, drift as a share of the path) and time per cloud on long
    simulated ToF sweeps along the deck plate's girder (:func:`_sweeps`, the first ``limit``
    clouds), for this pipeline, odometry alone and Open3D's tutorial pipeline (FPFH +
    RANSAC + ICP, cloud to cloud); then the pose-graph optimisation of long sessions
    against Open3D's (:mod:`bench.map_graph`)."""
    from bench.map_structures import bench_map_structures

    yield from (
        bench_map_structures(1, max(limit, 3), commands=1) if limit else bench_map_structures()
    )
    for label, config in _sweeps():
        yield from _route(label, config, limit)
    from bench.map_graph import bench_map_graph

    yield from bench_map_graph(limit)


STRUCTURE_POINTS = 30  # points off the deck plate for a cloud to say anything beyond it


def sees_structure(
    pcds: list[Any], truth: NDArray[np.float64], plate_z_m: float = 0.0, tol_m: float = 0.01
) -> NDArray[np.bool_]:
    """Which clouds (selected, sensor frame) have at least :data:`STRUCTURE_POINTS` points
    off the simulator's deck plate (world z = ``plate_z_m``) where they truly are: a plate
    alone fixes height, roll and pitch only, so the rest of such a cloud's step can come
    from nothing but odometry."""
    out = np.zeros(len(pcds), bool)
    for k, pcd in enumerate(pcds):
        pts = np.asarray(pcd.points)
        if len(pts):
            z = pts @ truth[k][2, :3] + truth[k][2, 3]
            out[k] = int((np.abs(z - plate_z_m) > tol_m).sum()) >= STRUCTURE_POINTS
    return out


def oracle_poses(
    truth: NDArray[np.float64], odometry: NDArray[np.float64], seen: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """What a perfect cloud-to-cloud registration would give without loop closures: the
    true step between consecutive clouds that both see structure, the odometry's otherwise
    (a reference for routes that do not return, not a strict bound: constraints that skip
    a blind cloud, or re-localisation in the map, could do better)."""
    poses = [odometry[0]]
    for k in range(len(truth) - 1):
        step_of = truth if seen[k] and seen[k + 1] else odometry
        poses.append(poses[-1] @ np.linalg.inv(step_of[k]) @ step_of[k + 1])
    return np.array(poses)


def _open3d_tutorial_poses(pcds: list[Any], odometry: NDArray[np.float64]) -> NDArray[np.float64]:
    """Open3D's global-registration tutorial, applied cloud to cloud and chained (the
    odometry's step where a cloud has too few points to describe)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    voxel = 0.02
    usable = [len(p.points) >= 30 and p.has_normals() for p in pcds]
    feats = [
        reg.compute_fpfh_feature(
            p, o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 5, max_nn=100)
        )
        if ok
        else None
        for p, ok in zip(pcds, usable)
    ]
    poses = [odometry[0]]
    for i in range(1, len(pcds)):
        if not (usable[i] and usable[i - 1]):
            poses.append(poses[-1] @ np.linalg.inv(odometry[i - 1]) @ odometry[i])
            continue
        # its warnings would break the output of one JSON object per line
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            ransac = reg.registration_ransac_based_on_feature_matching(
                pcds[i],
                pcds[i - 1],
                feats[i],
                feats[i - 1],
                True,
                voxel * 1.5,
                reg.TransformationEstimationPointToPoint(False),
                3,
                [
                    reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                    reg.CorrespondenceCheckerBasedOnDistance(voxel * 1.5),
                ],
                reg.RANSACConvergenceCriteria(100000, 0.999),
            )
        icp = reg.registration_icp(
            pcds[i],
            pcds[i - 1],
            voxel * 0.4 * 3,
            ransac.transformation,
            reg.TransformationEstimationPointToPlane(),
        )
        poses.append(poses[-1] @ icp.transformation)
    return np.array(poses)
