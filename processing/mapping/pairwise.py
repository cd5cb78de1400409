"""Each cloud registered to the few clouds just before it, from the odometry's steps.

What this finds depends only on the clouds and their odometry, never on another cloud's
optimised pose: the selected cloud, its large planes, the step into it (ICP's correction
kept along the directions the geometry observes) and the ICP edges to its predecessors
with their point-to-plane information. A long session's runs of clouds can thus be
measured apart, on several workers (:func:`measure_run`), and joined into one pose graph
(:meth:`processing.mapping.incremental.IncrementalMap.attach`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from processing.mapping.icp import (
    constrain_to_observable,
    plane_information,
    register_pair,
    structure_share,
)
from processing.mapping.params import IcpParams, MapParams
from processing.mapping.planes import Plane, extract_planes
from processing.mapping.selection import select

Facts = tuple[float, float, bool, int]  # fitness, RMSE, placed by odometry, degenerate dims


@dataclass
class PairEdge:
    """An ICP edge into an earlier cloud ``target``: T_target_cloud (4, 4) and its
    point-to-plane information (6, 6, in the cloud's frame)."""

    target: int
    transformation: NDArray[np.float64]
    information: NDArray[np.float64]


@dataclass
class Step:
    """The step (4, 4) from the previous cloud into this one: the odometry's (or, without
    odometry, the previous step again), the registered ``seed`` that places the cloud, its
    facts, the heading ICP found against the odometry's (a rotation vector, where the
    structure fixes it) and the ICP edge to the previous cloud."""

    step: NDArray[np.float64]
    seed: NDArray[np.float64]
    facts: Facts
    heading_gap: NDArray[np.float64] | None
    edge: PairEdge | None


@dataclass
class CloudMeasurement:
    """One cloud as selected (points, normals: (K, 3) sensor frame), its large planes, the
    step into it (None for a session's first cloud) and its ICP edges to the clouds before
    the previous one."""

    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    planes: list[Plane]
    step: Step | None
    edges: list[PairEdge]

    def cloud(self) -> o3d.geometry.PointCloud:
        """The selected cloud as Open3D's (normals as measured)."""
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))
        if len(self.normals):
            pcd.normals = o3d.utility.Vector3dVector(self.normals)
        return pcd


def edge_of(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    j: int,
    init: NDArray[np.float64],
    params: IcpParams,
) -> PairEdge | None:
    """The ICP edge from ``source`` to cloud ``j`` (``target``) from ``init`` (T_j_source);
    None where the registration failed (:func:`register_pair`)."""
    result = register_pair(source, target, init, params)
    if result is None:
        return None
    info = plane_information(source, target, result, params)
    return PairEdge(j, np.asarray(result.transformation).copy(), info)


def measure_step(
    pcd: o3d.geometry.PointCloud,
    previous: o3d.geometry.PointCloud,
    step: NDArray[np.float64],
    has_odometry: bool,
    i: int,
    params: IcpParams,
    tracked: Facts | None = None,
) -> Step:
    """Cloud ``i`` registered to the previous one from ``step``. Where the step comes from
    ``tracked`` registration (to the map, which holds the previous cloud) it is kept and
    only the edge is measured; else ICP's correction is kept along the directions the
    geometry observes, or all of it without odometry (ICP's weak evidence beats a guess)."""
    result = register_pair(pcd, previous, step, params)
    edge = None
    if result is not None:
        info = plane_information(pcd, previous, result, params)
        edge = PairEdge(i - 1, np.asarray(result.transformation).copy(), info)
    if tracked is not None:
        return Step(step, step, tracked, None, edge)
    if result is None:
        return Step(step, step, (0.0, 0.0, True, 6), None, None)
    seed, degenerate = constrain_to_observable(step, result, pcd, previous, params)
    if not has_odometry:
        seed = np.asarray(result.transformation).copy()
    facts = (float(result.fitness), float(result.inlier_rmse), False, degenerate)
    gap = None
    # ICP's heading is trustworthy where the match is close and structure, not only the
    # plate, fixes it
    if has_odometry and result.fitness >= 0.9 and structure_share(pcd) >= 0.15:
        T = np.asarray(result.transformation)
        gap = Rotation.from_matrix(T[:3, :3] @ step[:3, :3].T).as_rotvec()
    return Step(step, seed, facts, gap, edge)


def measure_run(
    clouds: Sequence[NDArray[np.floating]],
    guesses: NDArray[np.float64],
    first: int,
    context: int,
    params: MapParams,
    shape: tuple[int, int] | None = None,
) -> list[CloudMeasurement]:
    """Measurements of a run of consecutive clouds with odometry.

    ``clouds`` (each (K, 3), sensor frame) are clouds ``first - context`` onwards of the
    session with their odometry poses ``guesses`` (len(clouds), 4, 4); the first
    ``context`` of them (``params.neighbours`` clouds, fewer at the session's start) are
    only registered to, and the measurements of the others are returned, equal to those
    of the whole session measured at once. Each cloud's edges to the clouds before its
    predecessor start from the registered steps between them.
    """
    pcds = [select(c, params.select, shape) for c in clouds]
    seeds: list[NDArray[np.float64]] = [np.eye(4)]  # seeds[k]: step into pcds[k]
    out = []
    for k, pcd in enumerate(pcds):
        i = first - context + k
        step = None
        if k > 0:
            odometry = np.linalg.inv(guesses[k - 1]) @ guesses[k]
            step = measure_step(pcd, pcds[k - 1], odometry, True, i, params.icp)
            seeds.append(step.seed)
        if k < context:
            continue
        edges: list[PairEdge] = []
        if params.pose_graph:
            relative = np.eye(4) if step is None else step.seed.copy()
            for back in range(2, params.neighbours + 1):
                if k - back < 0:
                    break
                relative = seeds[k - back + 1] @ relative  # T_(i-back)_i
                edge = edge_of(pcd, pcds[k - back], i - back, relative, params.icp)
                if edge is not None:
                    edges.insert(0, edge)  # the earliest cloud's first
        planes = (
            extract_planes(np.asarray(pcd.points), np.asarray(pcd.normals))
            if params.planes.enabled and pcd.has_normals()
            else []
        )
        normals = np.asarray(pcd.normals) if pcd.has_normals() else np.zeros((0, 3))
        out.append(
            CloudMeasurement(np.asarray(pcd.points).copy(), normals.copy(), planes, step, edges)
        )
    return out
