"""3D map of the structure from ToF clouds by ICP (paper §3.2), drift-free by a pose graph.

The paper's four steps, each a small function:

1. **selection** (:func:`select`): invalid and far returns dropped, the organised depth
   image median-filtered when the cloud is organised, voxel downsampling, normals;
2. **matching** (:func:`match`): the odometry gives the initial alignment; FPFH features on
   the roughly aligned clouds then propose a finer one, kept only when it stays within
   the odometry's error bounds (repeating stiffeners make features ambiguous);
3. **rejection**: correspondences farther than ``max_correspondence_m`` are dropped and the
   rest weighted by a robust Tukey loss, so outliers and duplicates carry no weight;
4. **alignment** (:func:`align`): point-to-plane (default), point-to-point or generalized
   ICP (plane-to-plane). On a small patch of flat plate point-to-plane's normal equations
   are singular and it can run away: the fitness and bounds checks catch that and the
   odometry is used (generalized ICP stays well-posed there but slides along the plate);

with the paper's three stopping rules (:class:`MapParams`): the error stops changing
(relative fitness and RMSE), an iteration cap, and a transform that leaves its bounds
(then the odometry is used and the cloud is flagged).

Beyond the paper: each cloud is aligned to a local map of the previous ones; then a pose
graph (Open3D) ties every cloud to its next few neighbours and to earlier clouds of the
same place (loop closures) and is optimised robustly, so the trajectory does not drift.
Along directions the geometry does not constrain (a flat plate says nothing about sliding
along it) ICP's correction is dropped and the odometry edge holds the pose; the result
reports how many such directions each cloud had.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

reg = o3d.pipelines.registration


@dataclass(frozen=True)
class MapParams:
    """Options of the map builder (lengths in metres, angles in degrees)."""

    # selection
    voxel_m: float = 0.02
    max_range_m: float = 4.0
    depth_median_px: int = 5  # median filter of an organised depth image (0: off)
    # matching
    use_fpfh: bool = False  # FPFH refinement of the odometry guess (ambiguous on repeating beams)
    fpfh_radius_m: float = 0.1
    # rejection and alignment
    metric: Literal["point_to_plane", "point_to_point", "generalized"] = "point_to_plane"
    max_correspondence_m: float = 0.06
    tukey_m: float = 0.03
    # stopping rules: error constant, iteration cap, transform out of bounds
    relative_fitness: float = 1e-6
    relative_rmse: float = 1e-6
    max_iterations: int = 30
    max_correction_m: float = 0.10
    max_correction_deg: float = 10.0
    min_fitness: float = 0.3
    # local map, degeneracy
    local_map_clouds: int = 6
    degenerate_ratio: float = 0.1
    # pose graph
    neighbours: int = 2  # edges from each cloud to the next few
    loop_radius_m: float = 0.25  # earlier clouds this close (sensor positions) are loop candidates
    loop_min_gap: int = 12  # ... and at least this many clouds back
    loop_min_fitness: float = 0.5
    loops_per_cloud: int = 2
    icp_sigma_m: float = 0.1  # effective error of one ICP correspondence, for the ICP edges' information
    odometry_sigma_frac: float = 0.05  # odometry error per step: this fraction of its length ...
    odometry_sigma_deg_per_m: float = 15.0  # ... and this heading error per metre driven
    odometry_sigma_floor_m: float = 0.002
    pose_graph: bool = True
    refine: bool = True  # False: the initial poses are better than ICP can do (visual odometry); only fuse
    map_voxel_m: float = 0.01


@dataclass
class MapResult:
    """Registered poses T_world_sensor (N, 4, 4), the fused map (M, 3) and per-cloud facts."""

    poses: NDArray[np.float64]
    points: NDArray[np.float32]
    fitness: NDArray[np.float64]
    rmse: NDArray[np.float64]
    used_odometry: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    degenerate_dims: NDArray[np.int_] = field(default_factory=lambda: np.zeros(0, int))
    loop_closures: int = 0
    pruned_edges: int = 0


def clean_cloud(points: NDArray[np.floating], max_range_m: float) -> NDArray[np.float64]:
    """Drop NaN/inf points and returns beyond ``max_range_m``; returns (K, 3) float64."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ok = np.isfinite(pts).all(axis=1)
    pts = pts[ok]
    return pts[np.linalg.norm(pts, axis=1) <= max_range_m]


def filter_organised(points: NDArray[np.floating], shape: tuple[int, int], median_px: int) -> NDArray[np.float64]:
    """Median-filter the depth of an organised cloud (H·W points, row-major), keeping each
    point on its pixel's ray: ToF noise is mostly along the ray."""
    h, w = shape
    pts = np.asarray(points, dtype=np.float64).reshape(h, w, 3)
    z = pts[..., 2].astype(np.float32)
    valid = np.isfinite(z)
    z_filled = np.where(valid, z, 0).astype(np.float32)
    med = cv2.medianBlur(z_filled, median_px) if median_px in (3, 5) else z_filled
    # where the neighbourhood is mostly invalid the median is 0: keep the raw value there
    good = valid & (med > 0) & (np.abs(med - z) < 0.05)
    scale = np.where(good, med / np.where(valid, z, 1), 1.0)
    out = pts * scale[..., None]
    out[~valid] = np.nan
    return out.reshape(-1, 3)


def select(points: NDArray[np.floating], params: MapParams = MapParams(), shape: tuple[int, int] | None = None) -> o3d.geometry.PointCloud:
    """Selection step: (organised) depth filtering, cleaning, voxel downsampling, normals."""
    if shape is not None and params.depth_median_px and np.asarray(points).reshape(-1, 3).shape[0] == shape[0] * shape[1]:
        points = filter_organised(points, shape, params.depth_median_px)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(clean_cloud(points, params.max_range_m)))
    pcd = pcd.voxel_down_sample(params.voxel_m)
    if len(pcd.points) >= 3:
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=params.voxel_m * 3, max_nn=30))
        pcd.orient_normals_towards_camera_location(np.zeros(3))
    return pcd


def within_bounds(init: NDArray[np.float64], T: NDArray[np.float64], params: MapParams) -> bool:
    """Stopping rule 3: the transform stayed within the odometry's error bounds."""
    d = np.linalg.inv(init) @ T
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(d[:3, :3]).as_rotvec()))
    return bool(np.linalg.norm(d[:3, 3]) <= params.max_correction_m and angle <= params.max_correction_deg)


def _fpfh(pcd: o3d.geometry.PointCloud, params: MapParams) -> reg.Feature:
    return reg.compute_fpfh_feature(pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=params.fpfh_radius_m, max_nn=100))


def match(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, init: NDArray[np.float64], params: MapParams) -> NDArray[np.float64]:
    """Matching step: the odometry's ``init``, refined by FPFH feature matching on the
    roughly aligned clouds (fast global registration) when enabled and when the
    refinement stays within bounds."""
    if not params.use_fpfh or len(source.points) < 30 or len(target.points) < 30:
        return init
    moved = o3d.geometry.PointCloud(source).transform(init)
    option = reg.FastGlobalRegistrationOption(maximum_correspondence_distance=params.max_correspondence_m)
    result = reg.registration_fgr_based_on_feature_matching(moved, target, _fpfh(moved, params), _fpfh(target, params), option)
    refined = result.transformation @ init
    return refined if result.fitness > params.min_fitness and within_bounds(init, refined, params) else init


def align(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, init: NDArray[np.float64], params: MapParams) -> reg.RegistrationResult:
    """Rejection and alignment steps: ICP with correspondences capped at
    ``max_correspondence_m`` and weighted by a Tukey loss, point-to-plane or point-to-point,
    stopped by the error-constant and iteration-cap rules."""
    kernel = reg.TukeyLoss(k=params.tukey_m)
    criteria = reg.ICPConvergenceCriteria(relative_fitness=params.relative_fitness, relative_rmse=params.relative_rmse,
                                          max_iteration=params.max_iterations)
    gicp = reg.TransformationEstimationForGeneralizedICP(epsilon=1e-3, kernel=kernel)
    if params.metric == "generalized":
        return reg.registration_generalized_icp(source, target, params.max_correspondence_m, init, gicp, criteria)
    estimator = (reg.TransformationEstimationPointToPlane(kernel) if params.metric == "point_to_plane"
                 else reg.TransformationEstimationPointToPoint())
    return reg.registration_icp(source, target, params.max_correspondence_m, init, estimator, criteria)


def register_clouds(
    clouds: Sequence[NDArray[np.floating]],
    initial_poses: NDArray[np.floating] | None = None,
    *,
    params: MapParams = MapParams(),
    shape: tuple[int, int] | None = None,
) -> MapResult:
    """Register clouds (each (K, 3), sensor frame) into one world map.

    Parameters
    ----------
    clouds : sequence of (K, 3) arrays; NaN rows are ignored.
    initial_poses : (N, 4, 4) odometry guesses of T_world_sensor, or None (the first cloud
        is the world frame and motion is estimated from geometry alone).
    shape : (H, W) when the clouds are organised depth images (enables depth filtering).
    """
    n = len(clouds)
    if n == 0:
        raise ValueError("clouds must not be empty")
    if initial_poses is not None:
        initial_poses = np.asarray(initial_poses, dtype=np.float64)
        if initial_poses.shape != (n, 4, 4):
            raise ValueError(f"initial_poses must be ({n}, 4, 4), one per cloud, got {initial_poses.shape}")
        if not np.isfinite(initial_poses).all():
            raise ValueError("initial_poses contain NaN or infinite values")
    pcds = [select(c, params, shape) for c in clouds]
    if not params.refine:
        if initial_poses is None:
            raise ValueError("refine=False needs initial poses")
        zeros = np.zeros(n)
        return MapResult(initial_poses.copy(), fuse_map(pcds, initial_poses, params.map_voxel_m), zeros, zeros, np.ones(n, bool), np.zeros(n, int))
    front = _front_end(pcds, initial_poses, params)
    poses, loops, pruned = front.poses, 0, 0
    if params.pose_graph and n > 2:
        steps = _odometry_steps(initial_poses, front.poses)
        poses, loops, pruned = _pose_graph(pcds, front.poses, steps, params)
    points = fuse_map(pcds, poses, params.map_voxel_m)
    return MapResult(poses, points, front.fitness, front.rmse, front.used_odometry, front.degenerate_dims, loops, pruned)


def _front_end(pcds: list[o3d.geometry.PointCloud], initial: NDArray[np.float64] | None, params: MapParams) -> MapResult:
    """Each cloud aligned to a local map of the previous ones, seeded by odometry."""
    n = len(pcds)
    guess = initial if initial is not None else np.repeat(np.eye(4)[None], n, axis=0)
    poses = np.zeros((n, 4, 4))
    fitness, rmse = np.zeros(n), np.zeros(n)
    used_odo = np.zeros(n, bool)
    degenerate = np.zeros(n, int)
    poses[0], fitness[0] = guess[0], 1.0
    for i in range(1, n):
        if initial is not None:
            delta = np.linalg.inv(guess[i - 1]) @ guess[i]
        else:  # constant-velocity guess without odometry
            delta = np.linalg.inv(poses[i - 2]) @ poses[i - 1] if i >= 2 else np.eye(4)
        init = poses[i - 1] @ delta
        target = _local_map(pcds, poses, i, params)
        poses[i], fitness[i], rmse[i], used_odo[i], degenerate[i] = front_end_step(pcds[i], target, init, params)
    return MapResult(poses, np.zeros((0, 3), np.float32), fitness, rmse, used_odo, degenerate)


def front_end_step(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, init: NDArray[np.float64],
                   params: MapParams) -> tuple[NDArray[np.float64], float, float, bool, int]:
    """One cloud's pose: matching, then ICP against the local map ``target``, kept only
    along observable directions and within the odometry's bounds. Returns (pose, fitness,
    rmse, whether the odometry was used instead, degenerate directions)."""
    if len(source.points) < 10 or len(target.points) < 10:
        return init, 0.0, 0.0, True, 6
    start = match(source, target, init, params)
    result = align(source, target, start, params)
    if result.fitness < params.min_fitness or not np.isfinite(result.transformation).all():
        return init, float(result.fitness), float(result.inlier_rmse), True, 6
    pose, degenerate = constrain_to_observable(init, result.transformation, source, target, params)
    if not within_bounds(init, pose, params):
        return init, float(result.fitness), float(result.inlier_rmse), True, degenerate
    return pose, float(result.fitness), float(result.inlier_rmse), False, degenerate


class IncrementalMap:
    """The map growing one cloud at a time, as the robot sends them (the live map): each
    cloud is placed by :func:`front_end_step` against a local map of the previous ones,
    seeded by its odometry, and fused into a voxel map. No pose graph: the job builds the
    final map when the session ends."""

    def __init__(self, params: MapParams = MapParams()) -> None:
        self.params = params
        self.poses: list[NDArray[np.float64]] = []
        self.used_odometry = 0
        self._guesses: list[NDArray[np.float64]] = []
        self._recent: list[tuple[o3d.geometry.PointCloud, NDArray[np.float64]]] = []  # the last clouds and poses
        self._fused = o3d.geometry.PointCloud()

    def add(self, points: NDArray[np.floating], guess: NDArray[np.floating], shape: tuple[int, int] | None = None) -> NDArray[np.float64]:
        """Place one cloud (sensor frame) given its odometry pose ``guess``; its pose."""
        guess = np.asarray(guess, dtype=np.float64)
        pcd = select(points, self.params, shape)
        if not self.poses:
            pose = guess
        else:
            init = self.poses[-1] @ np.linalg.inv(self._guesses[-1]) @ guess
            recent = [p for p, _ in self._recent]
            target = _local_map(recent, np.array([T for _, T in self._recent]), len(recent), self.params)
            pose, _, _, odometry, _ = front_end_step(pcd, target, init, self.params)
            self.used_odometry += int(odometry)
        self._recent = [*self._recent, (pcd, pose)][-self.params.local_map_clouds:]
        self._fused += o3d.geometry.PointCloud(pcd).transform(pose)
        self._fused = self._fused.voxel_down_sample(self.params.map_voxel_m)
        self.poses.append(pose)
        self._guesses.append(guess)
        return pose

    @property
    def points(self) -> NDArray[np.float32]:
        """The fused map so far, (M, 3) world frame."""
        return np.asarray(self._fused.points, dtype=np.float32)


def _odometry_steps(initial: NDArray[np.float64] | None, front: NDArray[np.float64]) -> NDArray[np.float64]:
    """Relative motion between consecutive clouds as odometry says (or the front end)."""
    src = initial if initial is not None else front
    return np.array([np.linalg.inv(src[k]) @ src[k + 1] for k in range(len(src) - 1)])


def _information(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, T: NDArray[np.float64], params: MapParams) -> NDArray[np.float64]:
    """Information matrix of an ICP edge: Open3D's per-correspondence sum (unit weights),
    scaled by the correspondences' error so that it weighs right against odometry."""
    info = np.asarray(reg.get_information_matrix_from_point_clouds(source, target, params.max_correspondence_m, T))
    return info / params.icp_sigma_m**2


def _pose_graph(pcds: list[o3d.geometry.PointCloud], poses: NDArray[np.float64], steps: NDArray[np.float64],
                params: MapParams) -> tuple[NDArray[np.float64], int, int]:
    """Optimise a pose graph of odometry edges, ICP edges to the next few clouds and loop
    closures to earlier clouds of the same place (robust: Open3D's line process prunes
    loop closures that disagree). Returns poses, loop closures added and edges pruned."""
    n = len(pcds)
    graph = reg.PoseGraph()
    for T in poses:
        graph.nodes.append(reg.PoseGraphNode(T))
    for k in range(n - 1):  # odometry: holds what the geometry cannot; its error grows with the step
        d = float(np.linalg.norm(steps[k][:3, 3]))
        sigma_t = max(params.odometry_sigma_frac * d, params.odometry_sigma_floor_m)
        sigma_r = np.radians(params.odometry_sigma_deg_per_m * d + 0.2)
        info = np.diag([1 / sigma_r**2] * 3 + [1 / sigma_t**2] * 3)
        graph.edges.append(reg.PoseGraphEdge(k + 1, k, steps[k], info, uncertain=False))
    for i in range(n):
        for j in range(i + 1, min(n, i + 1 + params.neighbours)):
            _add_icp_edge(graph, pcds, poses, j, i, params, uncertain=False)
    loops = 0
    positions = poses[:, :3, 3]
    tree = cKDTree(positions)
    for j in range(n):
        near = [i for i in tree.query_ball_point(positions[j], params.loop_radius_m) if i < j - params.loop_min_gap]
        near = sorted(near, key=lambda i: np.linalg.norm(positions[i] - positions[j]))[: params.loops_per_cloud]
        for i in near:
            loops += _add_icp_edge(graph, pcds, poses, j, i, params, uncertain=True, min_fitness=params.loop_min_fitness)
    edges_before = len(graph.edges)
    option = reg.GlobalOptimizationOption(max_correspondence_distance=params.max_correspondence_m, edge_prune_threshold=0.25,
                                          preference_loop_closure=1.0, reference_node=0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(), reg.GlobalOptimizationConvergenceCriteria(), option)
    out = np.array([np.asarray(node.pose) for node in graph.nodes])
    return out, loops, edges_before - len(graph.edges)


def _add_icp_edge(graph: reg.PoseGraph, pcds: list[o3d.geometry.PointCloud], poses: NDArray[np.float64], s: int, t: int,
                  params: MapParams, *, uncertain: bool, min_fitness: float | None = None) -> int:
    """Register cloud s to cloud t from the current estimate and add the edge (1 if added)."""
    if len(pcds[s].points) < 10 or len(pcds[t].points) < 10:
        return 0
    init = np.linalg.inv(poses[t]) @ poses[s]  # T_t_s
    result = align(pcds[s], pcds[t], init, params)
    if result.fitness < (min_fitness or params.min_fitness) or not within_bounds(init, result.transformation, params):
        return 0
    T = constrain_to_observable(init, result.transformation, pcds[s], pcds[t], params)[0]
    info = _information(pcds[s], pcds[t], T, params)
    graph.edges.append(reg.PoseGraphEdge(s, t, T, info, uncertain=uncertain))
    return 1


def constrain_to_observable(
    init: NDArray[np.float64],
    T_icp: NDArray[np.float64],
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    params: MapParams,
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


def _local_map(pcds: list[o3d.geometry.PointCloud], poses: NDArray[np.float64], i: int, params: MapParams) -> o3d.geometry.PointCloud:
    target = o3d.geometry.PointCloud()
    for j in range(max(0, i - params.local_map_clouds), i):
        target += o3d.geometry.PointCloud(pcds[j]).transform(poses[j])
    target = target.voxel_down_sample(params.voxel_m)
    if not target.has_normals():
        target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=params.voxel_m * 3, max_nn=30))
    return target


def fuse_map(pcds: Sequence[o3d.geometry.PointCloud], poses: NDArray[np.float64], voxel_m: float) -> NDArray[np.float32]:
    """All clouds in the world frame, voxel-filtered, as (M, 3) float32."""
    fused = o3d.geometry.PointCloud()
    for pcd, T in zip(pcds, poses):
        fused += o3d.geometry.PointCloud(pcd).transform(T)
    fused = fused.voxel_down_sample(voxel_m)
    return np.asarray(fused.points, dtype=np.float32)
