"""Aligning two visits' 3D maps of one structure: AFTER's map frame in BEFORE's.

The mosaics' registration gives the planar pose (:mod:`processing.history.align`); lifted
to 3D it starts point-to-plane ICP (Tukey-weighted, coarse to fine) between the two
fused maps. A plate alone does not hold a cloud in its own plane, so ICP's correction is
kept only along the directions the geometry observes (the web, stiffeners, flange edges:
:func:`processing.mapping.icp.constrain_to_observable`); along the others the mosaics'
pose stands. The result says how well the maps agree: the RMS distance of corresponding
points, the share of AFTER's points that found one, and how far the maps moved the
mosaics' pose.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from processing.mapping.icp import align, constrain_to_observable
from processing.mapping.params import IcpParams


class MapAlignmentError(ValueError):
    """The two maps share too little to be aligned."""


@dataclass(frozen=True)
class MapAlignParams:
    """How the maps are aligned: voxel size of the copies aligned (the maps' own
    resolution is a good choice), the correspondence distances coarse to fine, and how many
    points each map needs."""

    voxel_m: float = 0.01
    distances_m: Sequence[float] = field(default=(0.05, 0.02))
    min_points: int = 100
    min_fitness: float = 0.3
    degenerate_ratio: float = 0.1


@dataclass(frozen=True)
class MapAlignment:
    """AFTER's map frame in BEFORE's (4, 4), the RMS distance across the surfaces of
    corresponding points (m, point to plane),
    the share of AFTER's points that found one, how far the maps moved the starting pose
    (m, at AFTER's points), and the directions the geometry left to the start (0-6)."""

    after_to_before: NDArray[np.float64]
    rmse_m: float
    fitness: float
    correction_m: float
    degenerate: int


def _cloud(points: NDArray[np.floating], voxel_m: float) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pcd = pcd.voxel_down_sample(voxel_m)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel_m, max_nn=30))
    return pcd


def align_maps(
    before: NDArray[np.floating],
    after: NDArray[np.floating],
    start: NDArray[np.float64],
    params: MapAlignParams = MapAlignParams(),
) -> MapAlignment:
    """Align AFTER's map points (M, 3) to BEFORE's (N, 3) from ``start`` (4, 4: AFTER's
    frame in BEFORE's, e.g. the mosaics' planar pose lifted to 3D); MapAlignmentError when
    either map is too small or too little of AFTER finds BEFORE."""
    b, a = _cloud(before, params.voxel_m), _cloud(after, params.voxel_m)
    if len(b.points) < params.min_points or len(a.points) < params.min_points:
        raise MapAlignmentError("a map has too few points to align")
    icp = IcpParams(degenerate_ratio=params.degenerate_ratio, max_iterations=30)
    T = np.asarray(start, np.float64)
    result = None
    for d in params.distances_m:
        result = align(a, b, T, replace(icp, max_correspondence_m=d, tukey_m=d / 2))
        T = np.asarray(result.transformation)
    assert result is not None
    if result.fitness < params.min_fitness:
        raise MapAlignmentError(
            f"only {result.fitness:.0%} of the later map lies on the earlier one"
        )
    fine = replace(icp, max_correspondence_m=params.distances_m[-1])
    T, degenerate = constrain_to_observable(start, result, a, b, fine)
    pts = np.asarray(a.points)
    placed = pts @ T[:3, :3].T + T[:3, 3]
    moved = placed - (pts @ start[:3, :3].T + start[:3, 3])
    # the residual across the surfaces (point to plane): the maps' samples do not coincide
    dist, idx = cKDTree(np.asarray(b.points)).query(
        placed, distance_upper_bound=params.distances_m[-1]
    )
    near = np.isfinite(dist)
    across = np.einsum(
        "ij,ij->i",
        placed[near] - np.asarray(b.points)[idx[near]],
        np.asarray(b.normals)[idx[near]],
    )
    return MapAlignment(
        T,
        float(np.sqrt(np.mean(across**2))) if near.any() else float("inf"),
        float(near.mean()),
        float(np.max(np.linalg.norm(moved, axis=1))),
        degenerate,
    )
