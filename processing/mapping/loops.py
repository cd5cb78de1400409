"""Loop closures: a cloud tied to earlier clouds of the same place, seen the same way."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from processing.mapping.icp import mutual_overlap, register_pair, structure_fitness
from processing.mapping.params import LoopParams, MapParams

reg = o3d.pipelines.registration


def loop_candidates(poses: NDArray[np.float64], i: int, params: LoopParams) -> list[int]:
    """Earlier clouds (``min_gap`` or more back, poses T_world_sensor (N, 4, 4)) whose
    sensor is within ``radius_m`` of cloud i's and whose optical axis is within
    ``max_view_angle_deg`` of its own, nearest first, ``per_cloud`` at most: clouds looking
    another way (the other lane, driven the other way) see other things."""
    if i <= params.min_gap:
        return []
    earlier = poses[: i - params.min_gap]
    dist = np.linalg.norm(earlier[:, :3, 3] - poses[i, :3, 3], axis=1)
    facing = earlier[:, :3, 2] @ poses[i, :3, 2] >= np.cos(np.radians(params.max_view_angle_deg))
    dist[~facing] = np.inf
    out = []
    for j in np.argsort(dist)[: params.per_cloud]:
        if dist[j] > params.radius_m:
            break
        out.append(int(j))
    return out


def close_loop(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: NDArray[np.float64],
    params: MapParams,
    *,
    optimised: bool = False,
) -> reg.RegistrationResult | None:
    """A loop closure from ``source`` to an earlier cloud ``target`` starting at ``init``
    (T_target_source), searched coarse to fine (the drift accumulated by then can exceed
    ICP's reach) within the loop's bounds; kept when the structure, not only the plate,
    matched and the two views share most of what they see, else None. From ``optimised``
    poses, views that do not already overlap within ``prefilter_m`` (the optimised error
    is centimetres at most) are not searched: the neighbouring lanes' views, which ICP
    cannot tie, cost nothing."""
    p = params.loops
    if optimised and (
        min(len(source.points), len(target.points)) < params.icp.min_points
        or mutual_overlap(source, target, init, p.prefilter_m) < p.min_overlap
    ):
        return None
    result = register_pair(
        source,
        target,
        init,
        params.icp,
        coarse=p.search_m,
        min_fitness=p.min_fitness,
        bounds=(p.max_correction_m, p.max_correction_deg),
    )
    if result is None:
        return None
    if structure_fitness(source, result, p.min_structure_points) < p.min_structure_fitness:
        return None
    if p.min_overlap > 0 and (
        mutual_overlap(source, target, np.asarray(result.transformation), p.overlap_m)
        < p.min_overlap
    ):
        return None
    return result
