"""The map as a pose graph that grows one cloud at a time (the batch job and the live map)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from processing.mapping.graph_optimiser import GraphOptions, optimise_pose_graph
from processing.mapping.icp import plane_information
from processing.mapping.landmarks import PlaneLandmarks
from processing.mapping.loops import close_loop, loop_candidates
from processing.mapping.odometry_edges import (
    odometry_error_scale,
    odometry_information,
    odometry_sigma,
)
from processing.mapping.pairwise import CloudMeasurement, PairEdge, Step, edge_of, measure_step
from processing.mapping.params import MapParams
from processing.mapping.planes import Plane, extract_planes
from processing.mapping.result import MapResult
from processing.mapping.selection import fuse_map, select
from processing.mapping.tracking import Tracker
from processing.mapping.wheels import WheelModel, fit_wheel_model, wheel_edge

reg = o3d.pipelines.registration


@dataclass
class MapCloud:
    """What the map keeps of one cloud: the points it was registered with, its odometry
    pose, the step into it (odometry, or the seed without), how its registration went,
    and what its odometry edge is worth."""

    pcd: o3d.geometry.PointCloud
    guess: NDArray[np.float64] | None  # odometry pose T_world_sensor, if the robot sent one
    step: NDArray[np.float64] | None = None  # odometry (or seed) step into it; None: the first
    fitness: float = 1.0
    rmse: float = 0.0
    used_odometry: bool = False
    degenerate_dims: int = 0
    odometry_sigma: tuple[float, float] | None = None  # configured (rotation rad, translation m)
    # information of its tracked pose (the geometry's where it observes, the prediction's
    # prior elsewhere): its odometry edge's once the wheel model holds the steps
    tracked_information: NDArray[np.float64] | None = None
    # ICP's heading step minus the odometry's, where the structure fixes it, over its
    # configured error
    heading_gap: float | None = None


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
        # the nodes' poses (the first len(graph.nodes) rows)
        self._pose_buffer = np.zeros((64, 4, 4))
        self.loop_closures = 0
        self._looped: set[tuple[int, int]] = set()  # (i, j) pairs tied by a loop closure
        self.pruned_edges = 0
        self.clouds: list[MapCloud] = []
        self.landmarks = PlaneLandmarks(params.planes)
        self._fused = o3d.geometry.PointCloud()
        self._fused_upto = 0  # clouds fused into ``_fused`` at their current pose
        self.tracker = Tracker(params.tracking, params.select.voxel_m)
        self.wheel_model: WheelModel | None = None  # fitted in :meth:`result`

    @property
    def usable_clouds(self) -> int:
        """Clouds with enough points after selection to be registered."""
        return sum(len(c.pcd.points) >= self.params.icp.min_points for c in self.clouds)

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
        uncertain: bool = False,
    ) -> NDArray[np.float64]:
        """Place one cloud (sensor frame) given its odometry pose ``guess`` (``uncertain``: a
        step less precise than those before it); its pose."""
        pose_guess = None if guess is None else np.asarray(guess, dtype=np.float64)
        # 1. selection: filter, downsample, normals
        pcd = select(points, self.params.select, shape)
        i = len(self.clouds)
        # 2. tracking, where enabled: the tracked pose is the graph's odometry
        tracked_information = None
        if self.params.tracking.enabled:
            pose_guess = self.tracker.track(pcd, pose_guess, uncertain)
            tracked_information = self.tracker.information()
        # 3. the step from the previous cloud: odometry (or the last step), corrected by ICP
        step = None
        if i > 0:
            previous = self.clouds[i - 1].guess
            if pose_guess is not None and previous is not None:
                odometry = np.linalg.inv(previous) @ pose_guess
            else:
                odometry = self._last_step()
            tracked = self._tracked_facts(len(pcd.points)) if self.params.tracking.enabled else None
            step = measure_step(
                pcd,
                self.clouds[i - 1].pcd,
                odometry,
                pose_guess is not None,
                i,
                self.params.icp,
                tracked,
            )
        # 4. edges to the clouds a few steps back (a tracked cloud was registered to every
        # cloud before it: edges beyond the previous one add nothing measurable there)
        edges = []
        if self.params.pose_graph and step is not None and not self.params.tracking.enabled:
            pose = np.asarray(self.graph.nodes[i - 1].pose) @ step.seed
            for j in range(max(0, i - self.params.neighbours), i - 1):
                init = np.linalg.inv(np.asarray(self.graph.nodes[j].pose)) @ pose
                edge = edge_of(pcd, self.clouds[j].pcd, j, init, self.params.icp)
                if edge is not None:
                    edges.append(edge)
        # 5. its large planes, landmarks of the map
        planes = (
            extract_planes(np.asarray(pcd.points), np.asarray(pcd.normals))
            if self.params.planes.enabled and pcd.has_normals()
            else []
        )
        # 6. into the graph: node, odometry and ICP edges, landmarks, loop closures
        return self._attach(
            MapCloud(pcd, pose_guess, tracked_information=tracked_information), planes, step, edges
        )

    def _last_step(self) -> NDArray[np.float64]:
        """The step into the latest cloud that has one (the constant-velocity guess)."""
        return next((c.step for c in reversed(self.clouds) if c.step is not None), np.eye(4))

    def attach(
        self, measured: CloudMeasurement, guess: NDArray[np.floating] | None = None
    ) -> NDArray[np.float64]:
        """Place the next cloud as measured apart (:func:`~processing.mapping.pairwise.
        measure_run`) given its odometry pose ``guess``; its pose. Clouds attached in order
        give the graph :meth:`add` gives from the same clouds and odometry, edges to earlier
        clouds measured from the odometry's chain rather than the graph's current poses."""
        pose_guess = None if guess is None else np.asarray(guess, dtype=np.float64)
        cloud = MapCloud(measured.cloud(), pose_guess)
        return self._attach(cloud, measured.planes, measured.step, measured.edges)

    def _attach(
        self, cloud: MapCloud, planes: list[Plane], step: Step | None, edges: list[PairEdge]
    ) -> NDArray[np.float64]:
        i = len(self.clouds)
        self.clouds.append(cloud)
        self.landmarks.planes.append(planes)
        if i == 0 or step is None:
            pose = cloud.guess if cloud.guess is not None else np.eye(4)
            self._append_node(pose)
            self.landmarks.associate(i, pose)
            return pose
        if step.heading_gap is not None:
            up = np.asarray(self.graph.nodes[i - 1].pose)[2, :3]  # the world's z in cloud i-1
            sigma = odometry_sigma(step.step, self.params.odometry)
            cloud.heading_gap = float(step.heading_gap @ up) / sigma[0]
        cloud.step = step.step if cloud.guess is not None else step.seed
        cloud.fitness, cloud.rmse, cloud.used_odometry, cloud.degenerate_dims = step.facts
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
        step = self.clouds[i].step
        assert step is not None
        self.clouds[i].odometry_sigma = odometry_sigma(step, self.params.odometry)
        info = self._odometry_information(i, 1.0)
        self.graph.edges.append(reg.PoseGraphEdge(i, i - 1, step, info, uncertain=False))

    def odometry_error_scale(self) -> float:
        """How much larger the odometry's heading error is than configured (>= 1), from the
        clouds' heading gaps so far (:func:`.odometry_edges.odometry_error_scale`)."""
        gaps = [c.heading_gap for c in self.clouds if c.heading_gap is not None]
        return odometry_error_scale(gaps, self.params.odometry)

    def _calibrate_odometry_edges(self) -> None:
        """Set every odometry edge's information for :meth:`odometry_error_scale` (each cloud's
        first certain edge to its predecessor is its odometry edge: it is added first)."""
        scale = self.odometry_error_scale()
        seen: set[int] = set()
        for edge in self.graph.edges:
            s, t = edge.source_node_id, edge.target_node_id
            if edge.uncertain or t != s - 1 or s in seen or self.clouds[s].odometry_sigma is None:
                continue
            seen.add(s)
            edge.information = self._odometry_information(s, scale)

    def _odometry_information(self, i: int, scale: float) -> NDArray[np.float64]:
        """Information of cloud i's odometry edge (its configured errors times ``scale``)."""
        cloud = self.clouds[i]
        wheels = self.wheel_model is not None
        return odometry_information(cloud.odometry_sigma, cloud.tracked_information, wheels, scale)

    def _add_edge(
        self, s: int, t: int, result: reg.RegistrationResult | None, *, uncertain: bool
    ) -> int:
        """An ICP edge from cloud s to cloud t with its point-to-plane information (1 if added)."""
        if result is None:
            return 0
        info = plane_information(self.clouds[s].pcd, self.clouds[t].pcd, result, self.params.icp)
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
                self.clouds[i].pcd,
                self.clouds[j].pcd,
                self._relative(j, i),
                self.params,
                optimised=optimised,
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
        for k in range(self._fused_upto, len(self.clouds)):
            moved = o3d.geometry.PointCloud(self.clouds[k].pcd)
            moved.transform(poses[k])
            self._fused += moved
        if self._fused_upto < len(self.clouds):
            self._fused = self._fused.voxel_down_sample(self.params.map_voxel_m)
            self._fused_upto = len(self.clouds)
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
                sum(self._close_loops(i, optimised=True) for i in range(len(self.clouds)))
                or len(self.landmarks) < landmarks
            ):
                self.optimise()
        if self.params.pose_graph and self.params.tracking.enabled and self.params.wheels:
            self._hold_to_wheels()
        poses, clouds = self.poses, self.clouds
        return MapResult(
            poses,
            fuse_map([c.pcd for c in clouds], poses, self.params.map_voxel_m),
            np.array([c.fitness for c in clouds], float),
            np.array([c.rmse for c in clouds], float),
            np.array([c.used_odometry for c in clouds], bool),
            np.array([c.degenerate_dims for c in clouds], int),
            self.loop_closures,
            self.pruned_edges,
            self.odometry_error_scale(),
            self.plane_landmarks,
        )
