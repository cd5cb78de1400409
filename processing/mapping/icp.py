"""One pair of clouds: matching, rejection, alignment (ICP), and what the result is worth —
the edge's information, the directions it observes, how much of the structure matched."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from processing.mapping.params import IcpParams

reg = o3d.pipelines.registration


def within_bounds(init: NDArray[np.float64], T: NDArray[np.float64], params: IcpParams) -> bool:
    """Stopping rule 3: the transform stayed within the odometry's error bounds."""
    d = np.linalg.inv(init) @ T
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(d[:3, :3]).as_rotvec()))
    return bool(
        np.linalg.norm(d[:3, 3]) <= params.max_correction_m and angle <= params.max_correction_deg
    )


def _fpfh(pcd: o3d.geometry.PointCloud, params: IcpParams) -> reg.Feature:
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=params.fpfh_radius_m, max_nn=100)
    return reg.compute_fpfh_feature(pcd, search)  # type: ignore[call-arg]  # Open3D's stubs lack indices' default


def match(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: NDArray[np.float64],
    params: IcpParams,
) -> NDArray[np.float64]:
    """Matching step: the odometry's ``init``, refined by FPFH feature matching on the
    roughly aligned clouds (fast global registration) when enabled and when the
    refinement stays within bounds."""
    if not params.use_fpfh or len(source.points) < 30 or len(target.points) < 30:
        return init
    moved = o3d.geometry.PointCloud(source)
    moved.transform(init)
    option = reg.FastGlobalRegistrationOption(
        maximum_correspondence_distance=params.max_correspondence_m
    )
    result = reg.registration_fgr_based_on_feature_matching(
        moved, target, _fpfh(moved, params), _fpfh(target, params), option
    )
    refined = result.transformation @ init
    return (
        refined
        if result.fitness > params.min_fitness and within_bounds(init, refined, params)
        else init
    )


def align(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: NDArray[np.float64],
    params: IcpParams,
) -> reg.RegistrationResult:
    """Rejection and alignment steps: ICP with correspondences capped at
    ``max_correspondence_m`` and weighted by a Tukey loss, point-to-plane or point-to-point,
    stopped by the error-constant and iteration-cap rules."""
    kernel = reg.TukeyLoss(k=params.tukey_m)
    criteria = reg.ICPConvergenceCriteria(
        relative_fitness=params.relative_fitness,
        relative_rmse=params.relative_rmse,
        max_iteration=params.max_iterations,
    )
    gicp = reg.TransformationEstimationForGeneralizedICP(epsilon=1e-3, kernel=kernel)
    if params.metric == "generalized":
        return reg.registration_generalized_icp(
            source, target, params.max_correspondence_m, init, gicp, criteria
        )
    estimator = (
        reg.TransformationEstimationPointToPlane(kernel)
        if params.metric == "point_to_plane"
        else reg.TransformationEstimationPointToPoint()
    )
    return reg.registration_icp(
        source, target, params.max_correspondence_m, init, estimator, criteria
    )


def _structure_mask(normals: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Points whose normal is more than 35° from the dominant one (web, stiffeners, bolts,
    edges: not the plate)."""
    dominant = np.linalg.eigh(normals.T @ normals)[1][:, -1]
    return np.abs(normals @ dominant) < np.cos(np.radians(35))


def structure_share(pcd: o3d.geometry.PointCloud) -> float:
    """Share of a cloud's points that are structure (:func:`_structure_mask`), 0 without normals."""
    normals = np.asarray(pcd.normals)
    return float(_structure_mask(normals).mean()) if len(normals) else 0.0


def structure_fitness(
    source: o3d.geometry.PointCloud, result: reg.RegistrationResult, min_points: int
) -> float:
    """Share of the source's structure points (normals more than 35° from the dominant one:
    web, stiffeners, bolts, edges, not the plate) that found a correspondence; 0 with fewer
    than ``min_points`` of them. A loop closure that only matched the plate, or a parallel
    lane's different stretch of web, scores low (plain fitness, dominated by the plate, does not)."""
    normals = np.asarray(source.normals)
    if len(normals) == 0:
        return 0.0
    structure = _structure_mask(normals)
    if structure.sum() < min_points:
        return 0.0
    matched = np.zeros(len(normals), bool)
    matched[np.asarray(result.correspondence_set)[:, 0]] = True
    return float((matched & structure).sum() / structure.sum())


def mutual_overlap(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    T: NDArray[np.float64],
    distance_m: float,
) -> float:
    """The smaller of the shares of source and of target points within ``distance_m`` of
    the other cloud once ``T`` (target <- source) is applied: near-identical views score high,
    views from another lane or mid-turn, which share only part of what they see, low."""
    forward = reg.evaluate_registration(source, target, distance_m, T).fitness
    backward = reg.evaluate_registration(target, source, distance_m, np.linalg.inv(T)).fitness
    return float(min(forward, backward))


def register_pair(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: NDArray[np.float64],
    params: IcpParams,
    *,
    coarse: Sequence[float] = (),
    bounds: tuple[float, float] | None = None,
    min_fitness: float | None = None,
) -> reg.RegistrationResult | None:
    """Matching, rejection and alignment of one pair, first at the ``coarse``
    correspondence distances; None when too few points, too low a fitness or a
    transform out of bounds (stopping rule 3)."""
    if len(source.points) < params.min_points or len(target.points) < params.min_points:
        return None
    start = match(source, target, init, params)
    for dist in coarse:
        start = align(
            source, target, start, replace(params, max_correspondence_m=dist, tukey_m=dist / 2)
        ).transformation
    result = align(source, target, start, params)
    limits = (
        replace(params, max_correction_m=bounds[0], max_correction_deg=bounds[1])
        if bounds
        else params
    )
    if (
        result.fitness < (params.min_fitness if min_fitness is None else min_fitness)
        or not np.isfinite(result.transformation).all()
        or not within_bounds(init, result.transformation, limits)
    ):
        return None
    return result


def plane_information(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    result: reg.RegistrationResult,
    params: IcpParams,
) -> NDArray[np.float64]:
    """Information matrix of a point-to-plane ICP edge: the sum over the final
    correspondences of the Tukey weight times Jᵀ J over σ², J = [q × n, n] for the source
    point q and the target's normal n both in the SOURCE frame. Open3D's pose graph measures
    an edge's error in its source frame (rotation, then translation: ``X⁻¹ Tt⁻¹ Ts``,
    checked), so the information must be there too; in the target frame (as Open3D's
    ``get_information_matrix_from_point_clouds``) it is off by the edge's own rotation,
    tens of degrees in a turn. Along a direction no surface faces (sliding on a plate) it is zero."""
    pairs = np.asarray(result.correspondence_set)
    if len(pairs) == 0:
        return np.zeros((6, 6))
    T = np.asarray(result.transformation)
    q = np.asarray(source.points)[pairs[:, 0]]
    p, n = np.asarray(target.points)[pairs[:, 1]], np.asarray(target.normals)[pairs[:, 1]]
    r = np.einsum("ij,ij->i", q @ T[:3, :3].T + T[:3, 3] - p, n)
    w = np.clip(1 - (r / params.tukey_m) ** 2, 0, None) ** 2
    n_source = n @ T[:3, :3]  # rows Rᵀ n
    J = np.hstack([np.cross(q, n_source), n_source])
    return (J * w[:, None]).T @ J / params.icp_sigma_m**2


def constrain_to_observable(
    init: NDArray[np.float64],
    result: reg.RegistrationResult,
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    params: IcpParams,
) -> tuple[NDArray[np.float64], int]:
    """Keep ICP's correction (``result``, from ``init``) only along directions the geometry
    constrains.

    The point-to-plane Hessian over ICP's final correspondences (rows [(q-c)×n / s, n],
    about their centroid c, rotations scaled by the cloud's spread s so both are in metres)
    is decomposed as one 6x6 matrix; along eigen-directions weaker than
    ``degenerate_ratio`` of half its trace (a flat plate gives no constraint in its own
    plane, nor in rotation about its normal) the odometry's value is kept. Rotation and
    translation are projected together: a turn about points a metre ahead moves the sensor
    sideways, and keeping the one without the other would move it by centimetres.
    Returns the pose and the number of degenerate directions (0-6).
    """
    T_icp = np.asarray(result.transformation)
    pairs = np.asarray(result.correspondence_set)
    if len(pairs) < 10:
        return init, 6
    q = np.asarray(source.points)[pairs[:, 0]] @ T_icp[:3, :3].T + T_icp[:3, 3]
    normals = np.asarray(target.normals)[pairs[:, 1]]
    c = q.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((q - c) ** 2, axis=1)))) or 1.0
    J = np.hstack([np.cross(q - c, normals) / scale, normals])
    P, degenerate = eigen_projector(J.T @ J / len(q), params.degenerate_ratio)
    dT = T_icp @ np.linalg.inv(init)
    R = dT[:3, :3]
    x = np.concatenate([Rotation.from_matrix(R).as_rotvec() * scale, dT[:3, 3] + R @ c - c])
    x = P @ x
    R2 = Rotation.from_rotvec(x[:3] / scale).as_matrix()
    out = np.eye(4)
    out[:3, :3] = R2
    out[:3, 3] = c - R2 @ c + x[3:]
    return out @ init, degenerate


def eigen_projector(A: NDArray[np.float64], ratio: float) -> tuple[NDArray[np.float64], int]:
    """Projector onto eigen-directions of A whose eigenvalue is at least ``ratio``·trace/2."""
    evals, evecs = np.linalg.eigh(A)
    good = evals >= ratio * max(float(np.trace(A)) / 2, 1e-12)
    V = evecs[:, good]
    return V @ V.T, int((~good).sum())
