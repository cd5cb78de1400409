"""The map as a pose graph that grows one cloud at a time (the batch job and the live map)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from processing.mapping.graph_optimiser import GraphOptions, optimise_pose_graph
from processing.mapping.icp import plane_information
from processing.mapping.landmarks import PlaneLandmarks
from processing.mapping.loops import close_loop, loop_candidates
from processing.mapping.pairwise import CloudMeasurement, PairEdge, Step, edge_of, measure_step
from processing.mapping.params import MapParams
from processing.mapping.planes import Plane, extract_planes
from processing.mapping.selection import fuse_map, select
from processing.mapping.tracking import Tracker, axis_information
from processing.mapping.wheels import WheelModel, fit_wheel_model, wheel_edge

reg = o3d.pipelines.registration


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
    odometry_error_scale: float = (
        1.0  # the odometry's error measured against ICP, over the configured one (>= 1)
    )
    plane_landmarks: int = (
        0  # large planes (deck plate, web, stiffener faces) that tied the clouds seeing them
    )


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
        self._pose_buffer = np.zeros(
            (64, 4, 4)
        )  # the nodes' poses (the first len(graph.nodes) rows)
        self.loop_closures = 0
        self._looped: set[tuple[int, int]] = set()  # (i, j) pairs tied by a loop closure
        self.pruned_edges = 0
        self._pcds: list[o3d.geometry.PointCloud] = []
        self._guesses: list[NDArray[np.float64] | None] = []
        self._steps: list[NDArray[np.float64]] = []  # odometry (or seed) step into each cloud
        self._facts: list[
            tuple[float, float, bool, int]
        ] = []  # fitness, rmse, used odometry, degenerate dims
        self._odometry_sigmas: dict[
            int, tuple[float, float]
        ] = {}  # cloud -> configured (rotation rad, translation m) of its odometry edge
        self._heading_gaps: list[
            float
            # ICP's heading step minus the odometry's, where the structure fixes it, over its configured
            # error
        ] = []
        self.landmarks = PlaneLandmarks(params.planes)
        self._fused = o3d.geometry.PointCloud()
        self._fused_upto = 0  # clouds fused into ``_fused`` at their current pose
        self.tracker = Tracker(params.tracking, params.select.voxel_m)
        self.wheel_model: WheelModel | None = None  # fitted in :meth:`result`
        # cloud -> information of its tracked pose (the geometry's where it observes, the
        # prediction's prior elsewhere): its odometry edge's
        self._tracked_information: dict[int, NDArray[np.float64]] = {}

    @property
    def usable_clouds(self) -> int:
        """Clouds with enough points after selection to be registered."""
        return sum(len(pcd.points) >= self.params.icp.min_points for pcd in self._pcds)

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
            self._pose_buffer = np.concatenate(
                [self._pose_buffer, np.zeros_like(self._pose_buffer)]
            )
        self._pose_buffer[n - 1] = pose

    def add(
        self,
        points: NDArray[np.floating],
        guess: NDArray[np.floating] | None = None,
        shape: tuple[int, int] | None = None,
    ) -> NDArray[np.float64]:
        """Place one cloud (sensor frame) given its odometry pose ``guess``; its pose."""
        guess = None if guess is None else np.asarray(guess, dtype=np.float64)
        pcd = select(points, self.params.select, shape)
        i = len(self._pcds)
        if self.params.tracking.enabled:  # the tracked pose is the graph's odometry
            guess = self.tracker.track(pcd, guess)
            self._tracked_information[i] = self.tracker.information()
        step = None
        if i > 0:
            previous = self._guesses[i - 1]
            if guess is not None and previous is not None:
                odometry = np.linalg.inv(previous) @ guess
            else:
                odometry = self._steps[-1] if self._steps else np.eye(4)
            tracked = self._tracked_facts(len(pcd.points)) if self.params.tracking.enabled else None
            step = measure_step(
                pcd, self._pcds[i - 1], odometry, guess is not None, i, self.params.icp, tracked
            )
        edges = []
        # a tracked cloud was registered to every cloud before it (the step): edges beyond
        # the previous cloud add nothing measurable there, and cost a registration each
        if self.params.pose_graph and step is not None and not self.params.tracking.enabled:
            pose = np.asarray(self.graph.nodes[i - 1].pose) @ step.seed
            for j in range(max(0, i - self.params.neighbours), i - 1):
                init = np.linalg.inv(np.asarray(self.graph.nodes[j].pose)) @ pose
                edge = edge_of(pcd, self._pcds[j], j, init, self.params.icp)
                if edge is not None:
                    edges.append(edge)
        planes = (
            extract_planes(np.asarray(pcd.points), np.asarray(pcd.normals))
            if self.params.planes.enabled and pcd.has_normals()
            else []
        )
        return self._attach(pcd, planes, step, edges, guess)

    def attach(
        self, measured: CloudMeasurement, guess: NDArray[np.floating] | None = None
    ) -> NDArray[np.float64]:
        """Place the next cloud as measured apart (:func:`~processing.mapping.pairwise.
        measure_run`) given its odometry pose ``guess``; its pose. Clouds attached in order
        give the graph :meth:`add` gives from the same clouds and odometry, edges to earlier
        clouds measured from the odometry's chain rather than the graph's current poses."""
        guess = None if guess is None else np.asarray(guess, dtype=np.float64)
        return self._attach(measured.cloud(), measured.planes, measured.step, measured.edges, guess)

    def _attach(
        self,
        pcd: o3d.geometry.PointCloud,
        planes: list[Plane],
        step: Step | None,
        edges: list[PairEdge],
        guess: NDArray[np.float64] | None,
    ) -> NDArray[np.float64]:
        i = len(self._pcds)
        self._pcds.append(pcd)
        self._guesses.append(guess)
        self.landmarks.planes.append(planes)
        if i == 0 or step is None:
            pose = guess if guess is not None else np.eye(4)
            self._append_node(pose)
            self._facts.append((1.0, 0.0, False, 0))
            self.landmarks.associate(i, pose)
            return pose
        if step.heading_gap is not None:
            up = np.asarray(self.graph.nodes[i - 1].pose)[2, :3]  # the world's z in cloud i-1
            self._heading_gaps.append(
                float(step.heading_gap @ up) / self._odometry_sigma(step.step)[0]
            )
        self._steps.append(step.step if guess is not None else step.seed)
        self._facts.append(step.facts)
        pose = np.asarray(self.graph.nodes[i - 1].pose) @ step.seed
        self._append_node(pose)
        self._add_odometry_edge(i)
        if self.params.pose_graph:
            for edge in ([step.edge] if step.edge is not None else []) + edges:
                self.graph.edges.append(
                    reg.PoseGraphEdge(
                        i, edge.target, edge.transformation, edge.information, uncertain=False
                    )
                )
            self.landmarks.associate(i, pose)
            loops = self._close_loops(i)
            # every ``optimise_every`` clouds, and less often as the graph grows (each
            # optimisation and re-fusion costs time in proportion to the clouds so far)
            if self.optimise_every and (loops or (i + 1) % max(self.optimise_every, i // 10) == 0):
                self.optimise()
        return np.asarray(self.graph.nodes[i].pose)

    def _tracked_facts(self, points: int) -> tuple[float, float, bool, int]:
        """Fitness, RMSE (not measured: 0), placed by the prediction, degenerate directions of
        the cloud just tracked."""
        found = self.tracker.last
        if found is None:
            return 0.0, 0.0, True, 6
        return min(1.0, found.matched / max(points, 1)), 0.0, False, found.degenerate

    def _relative(self, t: int, s: int) -> NDArray[np.float64]:
        """T_t_s from the current estimate."""
        return np.linalg.inv(np.asarray(self.graph.nodes[t].pose)) @ np.asarray(
            self.graph.nodes[s].pose
        )

    def _add_odometry_edge(self, i: int) -> None:
        """Odometry edge into cloud i: holds what the geometry cannot; its error grows with the step."""
        step = self._steps[i - 1]
        sigma_r, sigma_t = self._odometry_sigmas[i] = self._odometry_sigma(step)
        info = self._odometry_information(i, 1.0)
        self.graph.edges.append(reg.PoseGraphEdge(i, i - 1, step, info, uncertain=False))

    def _odometry_sigma(self, step: NDArray[np.float64]) -> tuple[float, float]:
        """Configured error of an odometry step: rotation (rad) and translation (m)."""
        p = self.params
        d = float(np.linalg.norm(step[:3, 3]))
        return float(np.radians(p.odometry.sigma_deg_per_m * d + 0.2)), max(
            p.odometry.sigma_frac * d, p.odometry.sigma_floor_m
        )

    def odometry_error_scale(self) -> float:
        """How much larger the odometry's heading error is than configured (>= 1): the robust
        spread (1.4826 MAD) of its heading steps against ICP's, where the structure fixes
        them, each over its configured error; 1 until 10 such steps were seen. ICP's own
        error is in the spread, so odometry as good as configured stays at 1."""
        if not self.params.odometry.calibrate or len(self._heading_gaps) < 10:
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
            edge.information = self._odometry_information(s, scale)

    def _odometry_information(self, i: int, scale: float) -> NDArray[np.float64]:
        """Information of cloud i's odometry edge: once the wheel model holds the steps, its
        tracked pose's (the geometry's where it observes, the prediction's elsewhere:
        :meth:`Tracker.information`), else the configured odometry errors times ``scale``."""
        if self.wheel_model is not None and i in self._tracked_information:
            return self._tracked_information[i]
        sigma_r, sigma_t = self._odometry_sigmas[i]
        return axis_information(scale * sigma_r, scale * sigma_t)

    def _add_edge(
        self, s: int, t: int, result: reg.RegistrationResult | None, *, uncertain: bool
    ) -> int:
        """An ICP edge from cloud s to cloud t with its point-to-plane information (1 if added)."""
        if result is None:
            return 0
        info = plane_information(self._pcds[s], self._pcds[t], result, self.params.icp)
        self.graph.edges.append(
            reg.PoseGraphEdge(s, t, np.asarray(result.transformation), info, uncertain=uncertain)
        )
        return 1

    @property
    def plane_landmarks(self) -> int:
        """Landmarks seen often enough to tie the clouds that see them."""
        return self.landmarks.tying

    def _close_loops(self, i: int, *, optimised: bool = False) -> int:
        """Loop closures from cloud i to the nearest earlier clouds of the same place
        (:mod:`processing.mapping.loops`), from the current or the ``optimised`` poses;
        how many were added."""
        added = 0
        for j in loop_candidates(self.poses, i, self.params.loops):
            if (i, j) in self._looped:
                continue
            result = close_loop(
                self._pcds[i], self._pcds[j], self._relative(j, i), self.params, optimised=optimised
            )
            if self._add_edge(i, j, result, uncertain=True):
                self._looped.add((i, j))
                added += 1
        self.loop_closures += added
        return added

    def full_graph(self) -> tuple[reg.PoseGraph, list[int]]:
        """The graph to optimise: the clouds' nodes and edges (odometry edges calibrated:
        :meth:`odometry_error_scale`), then the nodes of the plane landmarks that tie clouds
        and their sighting edges; and those landmarks' indices."""
        self._calibrate_odometry_edges()
        n = len(self.graph.nodes)
        graph = reg.PoseGraph()
        for node in self.graph.nodes:
            graph.nodes.append(node)
        active, landmark_edges = self.landmarks.edges(
            n, lambda i: np.asarray(self.graph.nodes[i].pose)
        )
        for m in active:
            graph.nodes.append(reg.PoseGraphNode(self.landmarks.poses[m]))
        for edge in list(self.graph.edges) + landmark_edges:
            graph.edges.append(edge)
        return graph, active

    def optimise(self) -> None:
        """Optimise the pose graph with the plane landmarks' nodes (robust: the line process
        prunes loop closures and plane sightings that disagree;
        :func:`~processing.mapping.graph_optimiser.optimise_pose_graph`)."""
        if len(self.graph.nodes) < 3:
            return
        n = len(self.graph.nodes)
        graph, active = self.full_graph()
        graph = optimise_pose_graph(
            graph,
            GraphOptions(
                max_correspondence_m=self.params.icp.max_correspondence_m,
                preference=self.params.loops.preference,
            ),
        )
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
            self.landmarks.poses[m] = np.asarray(graph.nodes[node].pose).copy()
        self._fused_upto = 0  # every pose may have moved: fuse again

    def _hold_to_wheels(self) -> None:
        """Fit the robot's wheel model to the optimised poses (:mod:`processing.mapping.
        wheels`) and, where it fits, tie every step to it and optimise again, each tracked
        step then held by the odometry only where its view did not fix it."""
        poses = self.poses
        self.wheel_model = model = fit_wheel_model(poses, self.tracker.sigmas()[1])
        if model is None:
            return
        for i in range(1, len(poses)):
            measured, information = wheel_edge(model, np.linalg.inv(poses[i - 1]) @ poses[i])
            self.graph.edges.append(
                reg.PoseGraphEdge(i, i - 1, measured, information, uncertain=False)
            )
        self.optimise()

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
            landmarks = len(self.landmarks)
            self.landmarks.merge()
            if (
                sum(self._close_loops(i, optimised=True) for i in range(len(self._pcds)))
                or len(self.landmarks) < landmarks
            ):
                self.optimise()
        if self.params.pose_graph and self.params.tracking.enabled and self.params.wheels:
            self._hold_to_wheels()
        fitness, rmse, used, degenerate = (np.array(col) for col in zip(*self._facts))
        poses = self.poses
        return MapResult(
            poses,
            fuse_map(self._pcds, poses, self.params.map_voxel_m),
            fitness.astype(float),
            rmse.astype(float),
            used.astype(bool),
            degenerate.astype(int),
            self.loop_closures,
            self.pruned_edges,
            self.odometry_error_scale(),
            self.plane_landmarks,
        )
