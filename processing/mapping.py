"""3D map of the structure from ToF clouds by ICP (paper §3.2), drift-free by a pose graph.

The paper's four steps, each a small function:

1. **selection** (:func:`select`): invalid and far returns dropped, the organised depth
   image median-filtered and averaged in 2x2 blocks when the cloud is organised, voxel
   downsampling, normals;
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

Beyond the paper: each cloud is registered to the previous one from the odometry step
(the chain that seeds the trajectory, kept only along directions the geometry observes);
then a pose graph (Open3D) ties every cloud to its next few neighbours and to earlier
clouds of the same place, looking the same way (loop closures, searched coarse to fine
because the error accumulated by then can exceed ICP's reach, kept only when the
structure, not just the plate, matches and the two views share most of what they see,
and searched again from the optimised poses at the end) and is optimised robustly. Each
ICP edge carries the point-to-plane information of its correspondences
(:func:`plane_information`, in the edge's source frame, where Open3D measures its error),
so a flat plate says nothing about sliding along it and the odometry edges hold the
trajectory there; the result reports how many such directions each cloud had. The large
planes each cloud sees (the deck plate, the girder's web, the stiffeners' faces:
:mod:`processing.planes`) are landmarks with their own graph nodes: every cloud that sees
one is tied to it in the three directions a plane fixes, so heading, tilt and height do
not drift along a lane the way a chain of pairwise registrations does. The odometry
edges' errors are raised to what the data show (:meth:`IncrementalMap.odometry_error_scale`:
its heading steps against ICP's where the structure fixes them), so odometry worse than
configured does not pull the map off.
:class:`IncrementalMap` builds that graph one cloud at a time: the batch job and the live
map are the same code.

Known limits (measured, ``steelscan bench map`` and README): views 24 cm apart (the next
lane) or from mid-turn share too little for ICP to align them (it lands centimetres off
even from a 3 cm start), so only returns to the same lane close loops (the plane landmarks
tie lanes together); where the ToF sees only bare plate (a girder that ends with the
plate, turns sampled coarsely) the heading comes from the odometry until the web is in
view again; nothing but the stiffeners and the odometry fixes the distance along the girder.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from processing.planes import Plane, extract_planes, plane_edge, plane_frame, same_plane, to_frame

reg = o3d.pipelines.registration


@dataclass(frozen=True)
class MapParams:
    """Options of the map builder (lengths in metres, angles in degrees)."""

    # selection
    voxel_m: float = 0.02
    max_range_m: float = 4.0
    depth_median_px: int = 5  # median filter of an organised depth image (0: off)
    pixel_stride: int = 2  # ... then averaged in blocks of this many pixels squared
    # matching
    use_fpfh: bool = False  # FPFH refinement of the odometry guess (ambiguous on repeating beams)
    fpfh_radius_m: float = 0.1
    # rejection and alignment
    metric: Literal["point_to_plane", "point_to_point", "generalized"] = "point_to_plane"
    max_correspondence_m: float = 0.06
    tukey_m: float = 0.03
    # stopping rules: error constant, iteration cap, transform out of bounds
    relative_fitness: float = 1e-4
    relative_rmse: float = 1e-4
    max_iterations: int = 10  # from the odometry or the current estimate ICP converges in a few (more: no better, measured)
    max_correction_m: float = 0.10
    max_correction_deg: float = 10.0
    min_fitness: float = 0.6  # below it (mid-turn views that barely overlap) ICP lands centimetres off: odometry instead
    min_points: int = 10  # clouds with fewer points (after selection) are placed by odometry
    # degeneracy
    degenerate_ratio: float = 0.1
    # pose graph
    neighbours: int = 2  # edges from each cloud to the next few
    loop_radius_m: float = 0.25  # earlier clouds this close (sensor positions) are loop candidates ...
    loop_min_gap: int = 12  # ... at least this many clouds back ...
    loop_max_view_angle_deg: float = 45.0  # ... whose optical axes are this close
    loops_per_cloud: int = 2
    loop_search_m: tuple[float, ...] = (0.3, 0.15)  # coarse correspondence distances tried before a loop's ICP
    loop_max_correction_m: float = 0.3  # a loop closure may correct this much accumulated drift ...
    loop_max_correction_deg: float = 15.0  # ... and this much heading
    loop_min_fitness: float = 0.5  # it is kept when this share of its points matched ...
    loop_min_structure_fitness: float = 0.8  # ... and this share of its structure (not the plate)
    loop_min_structure_points: int = 50
    loop_min_overlap: float = 0.6  # ... and this share of each cloud lies within loop_overlap_m of the other (both ways)
    loop_overlap_m: float = 0.02
    loop_prefilter_m: float = 0.05  # from optimised poses a candidate must overlap this well before it is searched
    loop_preference: float = 1.0  # Open3D's line process: lower prunes disagreeing loop closures sooner
    icp_sigma_m: float = 0.06  # effective error of one point-to-plane residual (neighbouring residuals are correlated: > the noise)
    odometry_sigma_frac: float = 0.05  # odometry error per step: this fraction of its length ...
    odometry_sigma_deg_per_m: float = 15.0  # ... and this heading error per metre driven
    odometry_sigma_floor_m: float = 0.002
    calibrate_odometry: bool = True  # raise the odometry's errors (heading and distance) to the heading error measured against ICP
    pose_graph: bool = True
    plane_landmarks: bool = True  # large planes (deck plate, web, stiffener faces) as landmarks of the pose graph
    plane_max_angle_deg: float = 5.0  # a cloud's plane is a landmark's when this close in angle ...
    plane_max_offset_m: float = 0.03  # ... and in distance (current estimate)
    plane_sigma_m: float = 0.06  # effective error of one inlier's distance to its landmark
    plane_min_sightings: int = 3  # a landmark seen fewer times ties nothing
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
    odometry_error_scale: float = 1.0  # the odometry's error measured against ICP, over the configured one (>= 1)
    plane_landmarks: int = 0  # large planes (deck plate, web, stiffener faces) that tied the clouds seeing them


def clean_cloud(points: NDArray[np.floating], max_range_m: float) -> NDArray[np.float64]:
    """Drop NaN/inf points and returns beyond ``max_range_m``; returns (K, 3) float64."""
    pts = np.asarray(points).reshape(-1, 3)
    r2 = np.einsum("ij,ij->i", pts, pts)
    with np.errstate(invalid="ignore"):
        ok = r2 <= max_range_m**2  # NaN and inf compare False
    return pts[ok].astype(np.float64)


def filter_organised(points: NDArray[np.floating], shape: tuple[int, int], median_px: int, stride: int = 1) -> NDArray[np.float32]:
    """Median-filter the depth of an organised cloud (H·W points, row-major), keeping each
    point on its pixel's ray (ToF noise is mostly along the ray), then average the
    consistent pixels of ``stride`` x ``stride`` blocks (NaN where a block has none)."""
    h, w = shape
    pts = np.asarray(points, dtype=np.float32).reshape(h, w, 3)
    z = pts[..., 2]
    valid = np.isfinite(z)
    z_filled = np.where(valid, z, np.float32(0))
    med = cv2.medianBlur(z_filled, median_px) if median_px in (3, 5) else z_filled
    # where the neighbourhood is mostly invalid the median is 0: keep the raw value there
    with np.errstate(invalid="ignore", divide="ignore"):
        good = valid & (med > 0) & (np.abs(med - z) < 0.05)
        scale = np.where(good, med / z, np.float32(1))
    out = pts * scale[..., None]
    out[~valid] = np.nan
    if stride > 1:  # stride x stride blocks averaged (the voxels average them anyway): fewer points, less noise
        hb, wb = h // stride, w // stride
        ok = valid & good
        masked = np.where(ok[..., None], out, np.float32(0))
        crop = (slice(0, hb * stride), slice(0, wb * stride))
        # block means by OpenCV's area resampling (exact for a whole factor), of the
        # values with holes as 0 and of the valid mask: their ratio averages valid pixels only
        mean = cv2.resize(masked[crop], (wb, hb), interpolation=cv2.INTER_AREA)
        count = cv2.resize(ok[crop].astype(np.float32), (wb, hb), interpolation=cv2.INTER_AREA)
        with np.errstate(invalid="ignore", divide="ignore"):
            out = mean / count[..., None]
        out[count == 0] = np.nan
    return out.reshape(-1, 3)


def select(points: NDArray[np.floating], params: MapParams = MapParams(), shape: tuple[int, int] | None = None) -> o3d.geometry.PointCloud:
    """Selection step: (organised) depth filtering, cleaning, voxel downsampling, normals."""
    if shape is not None and params.depth_median_px and np.asarray(points).reshape(-1, 3).shape[0] == shape[0] * shape[1]:
        points = filter_organised(points, shape, params.depth_median_px, params.pixel_stride)
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
    if not params.refine:
        if initial_poses is None:
            raise ValueError("refine=False needs initial poses")
        pcds = [select(c, params, shape) for c in clouds]
        zeros = np.zeros(n)
        return MapResult(initial_poses.copy(), fuse_map(pcds, initial_poses, params.map_voxel_m), zeros, zeros, np.ones(n, bool), np.zeros(n, int))
    graph_map = IncrementalMap(params)
    for i, cloud in enumerate(clouds):
        graph_map.add(cloud, None if initial_poses is None else initial_poses[i], shape)
    if graph_map.usable_clouds == 0:  # e.g. clouds in millimetres: every point "beyond" range
        raise ValueError(f"no cloud has {params.min_points} or more points within {params.max_range_m} m of the sensor "
                         "(point clouds must be in metres)")
    return graph_map.result()


class IncrementalMap:
    """The map as a pose graph growing one cloud at a time, as the robot sends them.

    Each new cloud is registered to the previous one from its odometry step (without
    odometry: the previous step, a constant-velocity guess), which places it (ICP's
    correction kept only along observable directions) and gives a graph edge (all of it,
    with its point-to-plane information); then edges to the clouds a few steps back and
    loop closures to earlier clouds of the same place are added, and its large planes are
    matched to the plane landmarks seen so far (or start new ones; the landmarks' nodes and
    sighting edges join the graph when it is optimised). ``optimise_every`` > 0
    optimises the graph every that many clouds (a tenth of the clouds so far once that is
    more) and at each loop closure (the live map), else only in
    :meth:`result` (the batch job); both give the same kind of map.
    """

    def __init__(self, params: MapParams = MapParams(), optimise_every: int = 0) -> None:
        self.params = params
        self.optimise_every = optimise_every
        self.graph = reg.PoseGraph()
        self._pose_buffer = np.zeros((64, 4, 4))  # the nodes' poses (the first len(graph.nodes) rows)
        self.loop_closures = 0
        self._looped: set[tuple[int, int]] = set()  # (i, j) pairs tied by a loop closure
        self.pruned_edges = 0
        self._pcds: list[o3d.geometry.PointCloud] = []
        self._guesses: list[NDArray[np.float64] | None] = []
        self._steps: list[NDArray[np.float64]] = []  # odometry (or seed) step into each cloud
        self._facts: list[tuple[float, float, bool, int]] = []  # fitness, rmse, used odometry, degenerate dims
        self._odometry_sigmas: dict[int, tuple[float, float]] = {}  # cloud -> configured (rotation rad, translation m) of its odometry edge
        self._heading_gaps: list[float] = []  # ICP's heading step minus the odometry's, where the structure fixes it, over its configured error
        self._planes: list[list[Plane]] = []  # large planes of each cloud (sensor frame)
        self._landmarks: list[list[tuple[int, int]]] = []  # each landmark's sightings (cloud, plane index)
        self._landmark_poses: list[NDArray[np.float64]] = []  # T_world_landmark: a frame on the plane, z along its normal
        self._fused = o3d.geometry.PointCloud()
        self._fused_upto = 0  # clouds fused into ``_fused`` at their current pose

    @property
    def usable_clouds(self) -> int:
        """Clouds with enough points after selection to be registered."""
        return sum(len(pcd.points) >= self.params.min_points for pcd in self._pcds)

    @property
    def poses(self) -> NDArray[np.float64]:
        """Current T_world_sensor of every cloud so far, (N, 4, 4)."""
        return self._pose_buffer[: len(self.graph.nodes)].copy()

    def _append_node(self, pose: NDArray[np.float64]) -> None:
        """A graph node for the next cloud, its pose also kept in an array (reading every
        node's pose back from Open3D for each loop search made a long session quadratic)."""
        self.graph.nodes.append(reg.PoseGraphNode(pose))
        n = len(self.graph.nodes)
        if n > len(self._pose_buffer):
            self._pose_buffer = np.concatenate([self._pose_buffer, np.zeros_like(self._pose_buffer)])
        self._pose_buffer[n - 1] = pose

    def add(self, points: NDArray[np.floating], guess: NDArray[np.floating] | None = None,
            shape: tuple[int, int] | None = None) -> NDArray[np.float64]:
        """Place one cloud (sensor frame) given its odometry pose ``guess``; its pose."""
        guess = None if guess is None else np.asarray(guess, dtype=np.float64)
        pcd = select(points, self.params, shape)
        i = len(self._pcds)
        self._pcds.append(pcd)
        self._guesses.append(guess)
        self._planes.append(extract_planes(np.asarray(pcd.points), np.asarray(pcd.normals))
                            if self.params.plane_landmarks and pcd.has_normals() else [])
        if i == 0:
            pose = guess if guess is not None else np.eye(4)
            self._append_node(pose)
            self._facts.append((1.0, 0.0, False, 0))
            self._associate_planes(0)
            return pose
        previous = self._guesses[i - 1]
        if guess is not None and previous is not None:
            step = np.linalg.inv(previous) @ guess
        else:
            step = self._steps[-1] if self._steps else np.eye(4)
        result = _register(pcd, self._pcds[i - 1], step, self.params)
        if result is None:
            seed, facts = step, (0.0, 0.0, True, 6)
        else:
            seed, degenerate = constrain_to_observable(step, result, pcd, self._pcds[i - 1], self.params)
            if guess is None:  # no odometry to hold the weak directions: ICP's weak evidence beats a guess
                seed = np.asarray(result.transformation)
            facts = (float(result.fitness), float(result.inlier_rmse), False, degenerate)
            if guess is not None:
                self._record_heading_gap(i, step, result)
        self._steps.append(step if guess is not None else seed)
        self._facts.append(facts)
        pose = np.asarray(self.graph.nodes[i - 1].pose) @ seed
        self._append_node(pose)
        self._add_odometry_edge(i)
        if self.params.pose_graph:
            if result is not None:
                self._add_edge(i, i - 1, result, uncertain=False)
            for j in range(max(0, i - self.params.neighbours), i - 1):
                self._add_edge(i, j, _register(pcd, self._pcds[j], self._relative(j, i), self.params), uncertain=False)
            self._associate_planes(i)
            loops = self._close_loops(i)
            # every ``optimise_every`` clouds, and less often as the graph grows (each
            # optimisation and re-fusion costs time in proportion to the clouds so far)
            if self.optimise_every and (loops or (i + 1) % max(self.optimise_every, i // 10) == 0):
                self.optimise()
        return np.asarray(self.graph.nodes[i].pose)

    def _relative(self, t: int, s: int) -> NDArray[np.float64]:
        """T_t_s from the current estimate."""
        return np.linalg.inv(np.asarray(self.graph.nodes[t].pose)) @ np.asarray(self.graph.nodes[s].pose)

    def _add_odometry_edge(self, i: int) -> None:
        """Odometry edge into cloud i: holds what the geometry cannot; its error grows with the step."""
        step = self._steps[i - 1]
        sigma_r, sigma_t = self._odometry_sigmas[i] = self._odometry_sigma(step)
        info = np.diag([1 / sigma_r**2] * 3 + [1 / sigma_t**2] * 3)
        self.graph.edges.append(reg.PoseGraphEdge(i, i - 1, step, info, uncertain=False))

    def _odometry_sigma(self, step: NDArray[np.float64]) -> tuple[float, float]:
        """Configured error of an odometry step: rotation (rad) and translation (m)."""
        p = self.params
        d = float(np.linalg.norm(step[:3, 3]))
        return float(np.radians(p.odometry_sigma_deg_per_m * d + 0.2)), max(p.odometry_sigma_frac * d, p.odometry_sigma_floor_m)

    def _record_heading_gap(self, i: int, step: NDArray[np.float64], result: reg.RegistrationResult) -> None:
        """Heading difference between the odometry's step into cloud i and ICP's, kept when
        ICP's is trustworthy (a close match whose structure, not only the plate, fixes it)."""
        if result.fitness < 0.9 or structure_share(self._pcds[i]) < 0.15:
            return
        gap = Rotation.from_matrix(np.asarray(result.transformation)[:3, :3] @ step[:3, :3].T).as_rotvec()
        up = np.asarray(self.graph.nodes[i - 1].pose)[2, :3]  # the world's z axis in cloud i-1's frame
        self._heading_gaps.append(float(gap @ up) / self._odometry_sigma(step)[0])

    def odometry_error_scale(self) -> float:
        """How much larger the odometry's heading error is than configured (>= 1): the robust
        spread (1.4826 MAD) of its heading steps against ICP's, where the structure fixes
        them, each over its configured error; 1 until 10 such steps were seen. ICP's own
        error is in the spread, so odometry as good as configured stays at 1."""
        if not self.params.calibrate_odometry or len(self._heading_gaps) < 10:
            return 1.0
        return max(1.0, 1.4826 * float(np.median(np.abs(self._heading_gaps))))

    def _calibrate_odometry_edges(self) -> None:
        """Set every odometry edge's information for :meth:`odometry_error_scale` (each cloud's
        first certain edge to its predecessor is its odometry edge: it is added first)."""
        scale = self.odometry_error_scale()
        seen: set[int] = set()
        for edge in self.graph.edges:
            s, t = edge.source_node_id, edge.target_node_id
            if edge.uncertain or t != s - 1 or s in seen or s not in self._odometry_sigmas:
                continue
            seen.add(s)
            sigma_r, sigma_t = self._odometry_sigmas[s]
            edge.information = np.diag([1 / (scale * sigma_r) ** 2] * 3 + [1 / (scale * sigma_t) ** 2] * 3)

    def _add_edge(self, s: int, t: int, result: reg.RegistrationResult | None, *, uncertain: bool) -> int:
        """An ICP edge from cloud s to cloud t with its point-to-plane information (1 if added)."""
        if result is None:
            return 0
        info = plane_information(self._pcds[s], self._pcds[t], result, self.params)
        self.graph.edges.append(reg.PoseGraphEdge(s, t, np.asarray(result.transformation), info, uncertain=uncertain))
        return 1

    @property
    def plane_landmarks(self) -> int:
        """Landmarks seen often enough to tie the clouds that see them."""
        return sum(len(s) >= self.params.plane_min_sightings for s in self._landmarks)

    def _landmark_plane(self, m: int) -> Plane:
        """Landmark m as a plane in the world (its node's z axis and origin)."""
        T = self._landmark_poses[m]
        return Plane(T[:3, 2].copy(), float(-T[:3, 2] @ T[:3, 3]), T[None, :3, 3].copy())

    def _associate_planes(self, i: int) -> None:
        """Match cloud i's large planes to the landmarks (current estimate); an unmatched one
        becomes a landmark, its node a frame on the plane (z along its normal)."""
        p = self.params
        pose = np.asarray(self.graph.nodes[i].pose)
        for k, plane in enumerate(self._planes[i]):
            world = to_frame(plane, pose)
            m = next((m for m in range(len(self._landmarks))
                      if same_plane(world, self._landmark_plane(m), p.plane_max_angle_deg, p.plane_max_offset_m)), None)
            if m is None:
                self._landmarks.append([(i, k)])
                self._landmark_poses.append(plane_frame(world))
            else:
                self._landmarks[m].append((i, k))

    def _merge_landmarks(self) -> None:
        """Merge landmarks that the optimised poses show to be one plane (seen apart before)."""
        p = self.params
        m = 0
        while m < len(self._landmarks):
            other = next((o for o in range(m + 1, len(self._landmarks))
                          if same_plane(self._landmark_plane(m), self._landmark_plane(o), p.plane_max_angle_deg, p.plane_max_offset_m)), None)
            if other is None:
                m += 1
                continue
            self._landmarks[m] += self._landmarks.pop(other)
            self._landmark_poses.pop(other)

    def _landmark_edges(self, first_node: int) -> tuple[list[int], list[reg.PoseGraphEdge]]:
        """The landmarks seen often enough to tie clouds (their nodes numbered from
        ``first_node`` in that order) and the edges from each sighting to its landmark's
        node: :func:`plane_edge` against the plane z = 0 of the landmark's frame, uncertain
        (the robust optimisation can drop a sighting that disagrees), and a weak prior tying
        each landmark to its first sighting along what planes leave free."""
        p = self.params
        active = [m for m, sightings in enumerate(self._landmarks) if len(sightings) >= p.plane_min_sightings]
        edges = []
        on_plane = Plane(np.array([0.0, 0.0, 1.0]), 0.0, np.zeros((1, 3)))
        for node, m in enumerate(active, start=first_node):
            T_L = np.linalg.inv(self._landmark_poses[m])
            for i, k in self._landmarks[m]:
                measurement, info = plane_edge(self._planes[i][k], on_plane, T_L @ np.asarray(self.graph.nodes[i].pose), p.plane_sigma_m)
                edges.append(reg.PoseGraphEdge(i, node, measurement, info, uncertain=True))
            anchor = self._landmarks[m][0][0]
            edges.append(reg.PoseGraphEdge(anchor, node, T_L @ np.asarray(self.graph.nodes[anchor].pose), np.eye(6), uncertain=False))
        return active, edges

    def _close_loops(self, i: int, *, optimised: bool = False) -> int:
        """Loop closures from cloud i to the nearest earlier clouds of the same place,
        searched coarse to fine (the drift accumulated by then can exceed ICP's reach).
        From ``optimised`` poses, a candidate whose views do not already overlap within
        ``loop_prefilter_m`` (the optimised error is centimetres at most) is not searched:
        the neighbouring lanes' views, which ICP cannot tie, cost nothing."""
        p = self.params
        if i <= p.loop_min_gap:
            return 0
        poses = self.poses
        dist = np.linalg.norm(poses[: i - p.loop_min_gap, :3, 3] - poses[i, :3, 3], axis=1)
        # clouds looking another way (the other lane, driven the other way) see other things
        facing = poses[: i - p.loop_min_gap, :3, 2] @ poses[i, :3, 2] >= np.cos(np.radians(p.loop_max_view_angle_deg))
        dist[~facing] = np.inf
        added = 0
        for j in np.argsort(dist)[: p.loops_per_cloud]:
            if dist[j] > p.loop_radius_m:
                break
            if (i, int(j)) in self._looped:
                continue
            if optimised and min(len(self._pcds[i].points), len(self._pcds[int(j)].points)) < p.min_points:
                continue
            if optimised and mutual_overlap(self._pcds[i], self._pcds[int(j)], self._relative(int(j), i), p.loop_prefilter_m) < p.loop_min_overlap:
                continue
            result = _register(self._pcds[i], self._pcds[j], self._relative(int(j), i), p, coarse=p.loop_search_m,
                               min_fitness=p.loop_min_fitness, bounds=(p.loop_max_correction_m, p.loop_max_correction_deg))
            if result is not None and structure_fitness(self._pcds[i], result, p.loop_min_structure_points) < p.loop_min_structure_fitness:
                result = None
            if result is not None and p.loop_min_overlap > 0 and mutual_overlap(self._pcds[i], self._pcds[int(j)], np.asarray(result.transformation), p.loop_overlap_m) < p.loop_min_overlap:
                result = None
            if self._add_edge(i, int(j), result, uncertain=True):
                self._looped.add((i, int(j)))
                added += 1
        self.loop_closures += added
        return added

    def optimise(self) -> None:
        """Optimise the pose graph with the plane landmarks' nodes (robust: Open3D's line
        process prunes loop closures and plane sightings that disagree)."""
        if len(self.graph.nodes) < 3:
            return
        self._calibrate_odometry_edges()
        n = len(self.graph.nodes)
        graph = reg.PoseGraph()
        for node in self.graph.nodes:
            graph.nodes.append(node)
        active, landmark_edges = self._landmark_edges(n)
        for m in active:
            graph.nodes.append(reg.PoseGraphNode(self._landmark_poses[m]))
        for edge in list(self.graph.edges) + landmark_edges:
            graph.edges.append(edge)
        option = reg.GlobalOptimizationOption(max_correspondence_distance=self.params.max_correspondence_m,
                                              edge_prune_threshold=0.25, preference_loop_closure=self.params.loop_preference,
                                              reference_node=0)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                    reg.GlobalOptimizationConvergenceCriteria(), option)
        kept = reg.PoseGraph()
        for k in range(n):
            kept.nodes.append(graph.nodes[k])
        for edge in graph.edges:
            if edge.target_node_id < n:
                kept.edges.append(edge)
        self.pruned_edges += len(self.graph.edges) - len(kept.edges)
        self.graph = kept
        self._pose_buffer[:n] = [np.asarray(node.pose) for node in kept.nodes]
        for node, m in enumerate(active, start=n):
            self._landmark_poses[m] = np.asarray(graph.nodes[node].pose).copy()
        self._fused_upto = 0  # every pose may have moved: fuse again

    @property
    def points(self) -> NDArray[np.float32]:
        """The fused map so far, (M, 3) world frame."""
        poses = self.poses
        if self._fused_upto == 0:
            self._fused = o3d.geometry.PointCloud()
        for k in range(self._fused_upto, len(self._pcds)):
            self._fused += o3d.geometry.PointCloud(self._pcds[k]).transform(poses[k])
        if self._fused_upto < len(self._pcds):
            self._fused = self._fused.voxel_down_sample(self.params.map_voxel_m)
            self._fused_upto = len(self._pcds)
        return np.asarray(self._fused.points, dtype=np.float32)

    def result(self) -> MapResult:
        """Optimise, merge landmarks the optimised poses show to be one plane, search loop
        closures again from the optimised poses (cloud by cloud the search only had the
        estimate so far, which can be decimetres off with poor odometry) and optimise once
        more if either changed the graph; the poses, the fused map and the per-cloud facts."""
        if self.params.pose_graph:
            self.optimise()
            landmarks = len(self._landmarks)
            self._merge_landmarks()
            if sum(self._close_loops(i, optimised=True) for i in range(len(self._pcds))) or len(self._landmarks) < landmarks:
                self.optimise()
        fitness, rmse, used, degenerate = (np.array(col) for col in zip(*self._facts))
        poses = self.poses
        return MapResult(poses, fuse_map(self._pcds, poses, self.params.map_voxel_m), fitness.astype(float),
                         rmse.astype(float), used.astype(bool), degenerate.astype(int), self.loop_closures, self.pruned_edges,
                         self.odometry_error_scale(), self.plane_landmarks)


def _structure_mask(normals: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Points whose normal is more than 35° from the dominant one (web, stiffeners, bolts,
    edges: not the plate)."""
    dominant = np.linalg.eigh(normals.T @ normals)[1][:, -1]
    return np.abs(normals @ dominant) < np.cos(np.radians(35))


def structure_share(pcd: o3d.geometry.PointCloud) -> float:
    """Share of a cloud's points that are structure (:func:`_structure_mask`), 0 without normals."""
    normals = np.asarray(pcd.normals)
    return float(_structure_mask(normals).mean()) if len(normals) else 0.0


def structure_fitness(source: o3d.geometry.PointCloud, result: reg.RegistrationResult, min_points: int) -> float:
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


def mutual_overlap(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, T: NDArray[np.float64], distance_m: float) -> float:
    """The smaller of the shares of source and of target points within ``distance_m`` of
    the other cloud once ``T`` (target <- source) is applied: near-identical views score high,
    views from another lane or mid-turn, which share only part of what they see, low."""
    forward = reg.evaluate_registration(source, target, distance_m, T).fitness
    backward = reg.evaluate_registration(target, source, distance_m, np.linalg.inv(T)).fitness
    return float(min(forward, backward))


def _register(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, init: NDArray[np.float64], params: MapParams,
              *, coarse: Sequence[float] = (), bounds: tuple[float, float] | None = None,
              min_fitness: float | None = None) -> reg.RegistrationResult | None:
    """Matching, rejection and alignment of one pair, first at the ``coarse``
    correspondence distances; None when too few points, too low a fitness or a
    transform out of bounds (stopping rule 3)."""
    if len(source.points) < params.min_points or len(target.points) < params.min_points:
        return None
    start = match(source, target, init, params)
    for dist in coarse:
        start = align(source, target, start, replace(params, max_correspondence_m=dist, tukey_m=dist / 2)).transformation
    result = align(source, target, start, params)
    limits = replace(params, max_correction_m=bounds[0], max_correction_deg=bounds[1]) if bounds else params
    if (result.fitness < (params.min_fitness if min_fitness is None else min_fitness)
            or not np.isfinite(result.transformation).all() or not within_bounds(init, result.transformation, limits)):
        return None
    return result


def plane_information(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, result: reg.RegistrationResult,
                      params: MapParams) -> NDArray[np.float64]:
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
    params: MapParams,
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
    P, degenerate = _projector(J.T @ J / len(q), params.degenerate_ratio)
    dT = T_icp @ np.linalg.inv(init)
    R = dT[:3, :3]
    x = np.concatenate([Rotation.from_matrix(R).as_rotvec() * scale, dT[:3, 3] + R @ c - c])
    x = P @ x
    R2 = Rotation.from_rotvec(x[:3] / scale).as_matrix()
    out = np.eye(4)
    out[:3, :3] = R2
    out[:3, 3] = c - R2 @ c + x[3:]
    return out @ init, degenerate


def _projector(A: NDArray[np.float64], ratio: float) -> tuple[NDArray[np.float64], int]:
    """Projector onto eigen-directions of A whose eigenvalue is at least ``ratio``·trace/2."""
    evals, evecs = np.linalg.eigh(A)
    good = evals >= ratio * max(float(np.trace(A)) / 2, 1e-12)
    V = evecs[:, good]
    return V @ V.T, int((~good).sum())


def fuse_map(pcds: Sequence[o3d.geometry.PointCloud], poses: NDArray[np.float64], voxel_m: float) -> NDArray[np.float32]:
    """All clouds in the world frame, voxel-filtered, as (M, 3) float32."""
    fused = o3d.geometry.PointCloud()
    for pcd, T in zip(pcds, poses):
        fused += o3d.geometry.PointCloud(pcd).transform(T)
    fused = fused.voxel_down_sample(voxel_m)
    return np.asarray(fused.points, dtype=np.float32)
