"""Tracking: each cloud registered to the map of every earlier cloud, held by the odometry
only as far as the data show the odometry to be right.

A cloud registered to the previous cloud alone sees what that one saw; registered to the
map of all earlier clouds (cropped to where the prediction puts it) it also sees what the
robot saw a turn ago or a lane ago, so errors do not add up cloud by cloud. Each
registration (:func:`register_to_map`) is Gauss-Newton point-to-plane ICP with a
Geman-McClure kernel, searched coarse to fine, with the odometry's prediction as a prior in
the same cost: along directions the geometry fixes the points win, along those it leaves
free (sliding along a plate, a turn that sees little of the map) the prior holds.

How far the prediction is trusted is measured, not configured (KISS-ICP's adaptive
threshold, Vizzo et al. 2023, applied to the prior as well): the spread of the corrections
registration made to the predictions so far sets the prior's errors and the widest
correspondence search (three of those errors, moved out to the cloud's farthest point).
Until ``warm_up`` corrections were seen the prior is generous. Good odometry thus ends up
trusted to millimetres, poor odometry to centimetres, and no threshold is tied to one
sensor or structure; the last search distance is a multiple of the selection's voxel.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from processing.mapping.icp import eigen_projector
from processing.mapping.params import TrackingParams
from processing.mapping.voxel_map import VoxelMap
from processing.poses import se3_exp, se3_log


class Registration(NamedTuple):
    """A cloud's registered pose T_world_sensor (4, 4), the matches it rests on, the
    directions (0-6) the geometry left to the prediction at the last search distance, and
    the pose's information (6, 6; rotation first, in the sensor frame): the geometry's
    along the directions it observes, the prediction's prior along the rest."""

    pose: NDArray[np.float64]
    matched: int
    degenerate: int
    information: NDArray[np.float64]


def axis_information(sigma_rad: float, sigma_m: float) -> NDArray[np.float64]:
    """Information (6, 6; rotation first) of a pose whose error per axis is ``sigma_rad``
    in rotation and ``sigma_m`` in translation, independent across axes."""
    return np.diag([1 / sigma_rad**2] * 3 + [1 / sigma_m**2] * 3)


def search_distances(
    sigma_rad: float, sigma_m: float, reach_m: float, params: TrackingParams, voxel_m: float
) -> list[float]:
    """Correspondence distances, coarse to fine: from three errors of the motion (a rotation
    of ``sigma_rad`` per axis moves a point ``reach_m`` from the sensor by 2·r·sin(θ/2), a
    translation of ``sigma_m`` per axis by √3·σ) down to ``final_distance_voxels`` voxels,
    halving (a half within 1.5 times the last distance is the last distance)."""
    final = params.final_distance_voxels * voxel_m
    spread = 2 * reach_m * np.sin(sigma_rad * np.sqrt(3) / 2) + sigma_m * np.sqrt(3)
    distances = [float(np.clip(3 * spread, final, params.max_distance_m))]
    while distances[-1] > final:
        half = distances[-1] / 2
        distances.append(half if half >= 1.5 * final else final)
    return distances


def register_to_map(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    map_points: NDArray[np.float64],
    map_normals: NDArray[np.float64],
    prediction: NDArray[np.float64],
    prior_information: NDArray[np.float64],
    distances: list[float],
    params: TrackingParams,
) -> Registration:
    """Pose T_world_sensor (4, 4) of a cloud (``points``, ``normals``: (K, 3), sensor frame)
    against a map (``map_points``, ``map_normals``: (M, 3), world frame), the number of
    matches it rests on and the directions its geometry left to the prediction.

    Minimises Σ ρ(nᵀ(T q − p)) + eᵀ Λ e over T, ρ the Geman-McClure kernel of scale d/3 for
    each search distance d in turn, e = log(prediction⁻¹ T) the deviation from the
    ``prediction`` and Λ the ``prior_information`` (6, 6; rotation first). The motion is a
    right perturbation T·exp(δ): a residual's Jacobian is [q × Rᵀn, Rᵀn]. Matches whose
    normals disagree (``min_normal_cos``) are not used (a web's point is not matched to the
    plate beside it).
    """
    # sliding-midpoint tree: built in half the time and queried faster on surface samples
    tree = cKDTree(map_points, balanced_tree=False, compact_nodes=False)
    reach_m = float(np.sqrt(np.mean(np.einsum("ij,ij->i", points, points))))
    T = prediction.copy()
    P_inv = np.linalg.inv(prediction)
    matched = degenerate = 0
    information = prior_information
    for level, distance in enumerate(distances):
        scale = distance / 3
        last = level == len(distances) - 1
        tolerance = params.final_tolerance if last else params.coarse_tolerance
        # coarse to fine in points too: each halving of the distance doubles the density,
        # down to every point at the last (and never below what a registration needs)
        stride = min(
            2 ** (len(distances) - 1 - level), max(1, len(points) // (8 * params.min_points))
        )
        pts, nrm = points[::stride], normals[::stride]
        for _ in range(params.max_iterations):
            R = T[:3, :3]
            world = pts @ R.T + T[:3, 3]
            ok, nearest, n = _matches(tree, map_normals, world, nrm, R, distance, params)
            matched = len(ok)
            if matched < params.min_points:
                return Registration(prediction.copy(), matched, 6, prior_information)
            r = np.einsum("ij,ij->i", world[ok] - map_points[nearest], n)
            JwJ, Jwr = _normal_equations(pts[ok], n @ R, r, scale, stride)
            H_data, g_data, degenerate = observable_part(JwJ, Jwr, reach_m, params.degenerate_ratio)
            e = se3_log(P_inv @ T)
            H = H_data + prior_information
            g = g_data + prior_information @ e
            step = -np.linalg.solve(H, g)
            T = T @ se3_exp(step)
            # neighbouring residuals are correlated: each counts as one of ``icp_sigma_m``
            information = H_data * (scale / params.icp_sigma_m) ** 2 + prior_information
            if np.abs(step).max() < tolerance:
                break
    return Registration(T, matched, degenerate, information)


def _matches(
    tree: cKDTree,
    map_normals: NDArray[np.float64],
    world: NDArray[np.float64],
    normals: NDArray[np.float64],
    R: NDArray[np.float64],
    distance: float,
    params: TrackingParams,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """The points (``world``: placed in the world; ``normals``: sensor frame, turned by
    ``R``) with a map point (``tree`` of them) within ``distance`` whose normal agrees with
    theirs (``min_normal_cos``): their indices, those map points' and those map points'
    normals."""
    # one thread: a cloud is a few thousand points, and starting threads costs more
    gap, nearest = tree.query(world, distance_upper_bound=distance)
    ok = np.flatnonzero(np.isfinite(gap))
    n = map_normals[nearest[ok]]
    agree = np.abs(np.einsum("ij,ij->i", n, normals[ok] @ R.T)) > params.min_normal_cos
    ok, n = ok[agree], n[agree]
    return ok, nearest[ok], n


def _normal_equations(
    q: NDArray[np.float64],
    n_sensor: NDArray[np.float64],
    r: NDArray[np.float64],
    scale: float,
    stride: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Jᵀ W J and Jᵀ W r of the point-to-plane residuals ``r`` of the matched points ``q``
    (sensor frame) with their map normals ``n_sensor`` (in the sensor frame): J = [q × n, n],
    W the Geman-McClure weights of ``scale``, each point counting for the ``stride`` it
    stands for."""
    w = stride * (scale**2 / (scale**2 + r**2)) ** 2 / scale**2  # as if every point
    J = np.empty((len(q), 6))
    J[:, 0] = q[:, 1] * n_sensor[:, 2] - q[:, 2] * n_sensor[:, 1]  # q × n
    J[:, 1] = q[:, 2] * n_sensor[:, 0] - q[:, 0] * n_sensor[:, 2]
    J[:, 2] = q[:, 0] * n_sensor[:, 1] - q[:, 1] * n_sensor[:, 0]
    J[:, 3:] = n_sensor
    Jw = J.T * w
    return Jw @ J, Jw @ r


def observable_part(
    H: NDArray[np.float64], g: NDArray[np.float64], reach_m: float, ratio: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], int]:
    """The normal equations (H (6, 6), g (6,)) kept only along the directions the geometry
    observes: with rotations scaled by ``reach_m`` (the points' RMS distance, so both parts are
    in metres), eigen-directions of H weaker than ``ratio`` of half its trace are dropped
    (:func:`~processing.mapping.icp.eigen_projector`). Along a flat plate's own plane, or
    about its normal, noisy normals give point-to-plane a little spurious information that
    would slide the cloud; without it the prior holds there (degeneracy-aware registration,
    Zhang et al. 2016). Also returns how many directions were dropped."""
    S = np.diag([1 / reach_m] * 3 + [1.0] * 3)  # x_scaled = S⁻¹ x
    S_inv = np.diag([reach_m] * 3 + [1.0] * 3)
    Hs = S @ H @ S
    P, dropped = eigen_projector(Hs, ratio)
    return S_inv @ P @ Hs @ P @ S_inv, S_inv @ P @ S @ g, dropped


def register_near(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    seen: VoxelMap,
    prediction: NDArray[np.float64],
    sigmas: tuple[float, float],
    params: TrackingParams,
) -> Registration | None:
    """A cloud (``points``, ``normals``: (K, 3), sensor frame) registered
    (:func:`register_to_map`) to the part of the map ``seen`` around where ``prediction``
    puts it, held by a prior of the prediction's errors per axis (``sigmas``: rad, m) that
    also sets the search distances; None where the cloud or the map there has too few
    points."""
    if len(points) < params.min_points:
        return None
    sigma_rad, sigma_m = sigmas
    reach = float(np.sqrt(np.einsum("ij,ij->i", points, points).max()))
    distances = search_distances(sigma_rad, sigma_m, reach, params, seen.voxel_m)
    world = points @ prediction[:3, :3].T + prediction[:3, 3]
    map_points, map_normals = seen.crop(
        world.min(axis=0) - distances[0], world.max(axis=0) + distances[0]
    )
    if len(map_points) < params.min_points:
        return None
    return register_to_map(
        points,
        normals,
        map_points,
        map_normals,
        prediction,
        axis_information(sigma_rad, sigma_m),
        distances,
        params,
    )


class Tracker:
    """Poses of clouds as they come, each registered to the map of all earlier ones
    (:func:`register_to_map`), predicted by the odometry (or, without it, by the last
    motion) and held by it as far as the corrections so far show it right."""

    def __init__(self, params: TrackingParams = TrackingParams(), voxel_m: float = 0.02) -> None:
        self.params = params
        self.map = VoxelMap(voxel_m)
        self._poses: list[NDArray[np.float64]] = []
        self._guesses: list[NDArray[np.float64] | None] = []
        # mean square correction per axis: rotation, translation
        self._corrections: list[tuple[float, float]] = []
        self.last: Registration | None = None  # the last cloud's registration (None: predicted)

    def sigmas(self) -> tuple[float, float]:
        """The prediction's error per axis, rotation (rad) and translation (m): the RMS of the
        corrections so far (generous until ``warm_up`` of them), not below the minimum."""
        p = self.params
        if len(self._corrections) < p.warm_up:
            return float(np.radians(p.initial_sigma_deg)), p.initial_sigma_m
        rot, trans = np.sqrt(np.mean(self._corrections, axis=0))
        return max(float(rot), float(np.radians(p.min_sigma_deg))), max(float(trans), p.min_sigma_m)

    def information(self) -> NDArray[np.float64]:
        """Information (6, 6) of the last cloud's pose: its registration's, or the prior's
        where it was placed by the prediction."""
        if self.last is not None:
            return self.last.information
        return axis_information(*self.sigmas())

    def _prediction(self, guess: NDArray[np.float64] | None) -> NDArray[np.float64]:
        previous = self._guesses[-1] if self._guesses else None
        if guess is not None and previous is not None:
            return self._poses[-1] @ np.linalg.inv(previous) @ guess
        if len(self._poses) >= 2:  # the last motion again
            return self._poses[-1] @ np.linalg.inv(self._poses[-2]) @ self._poses[-1]
        return self._poses[-1].copy()

    def track(
        self,
        pcd: o3d.geometry.PointCloud,
        guess: NDArray[np.float64] | None = None,
        uncertain: bool = False,
    ) -> NDArray[np.float64]:
        """Pose T_world_sensor (4, 4) of the next cloud (selected, with normals) given its
        odometry pose ``guess`` (or None); an ``uncertain`` guess (one step of a less
        precise source than the steps before) is searched as widely as the first ones."""
        points = np.asarray(pcd.points, dtype=np.float64)
        normals = (
            np.asarray(pcd.normals, dtype=np.float64)
            if pcd.has_normals()
            else np.zeros_like(points)
        )
        self.last = None
        if not self._poses:
            pose = np.eye(4) if guess is None else guess.copy()
        else:
            prediction = self._prediction(guess)
            pose = prediction
            if pcd.has_normals():
                sigmas = self.sigmas()
                if uncertain:
                    wide = (
                        float(np.radians(self.params.initial_sigma_deg)),
                        self.params.initial_sigma_m,
                    )
                    sigmas = (max(sigmas[0], wide[0]), max(sigmas[1], wide[1]))
                found = register_near(points, normals, self.map, prediction, sigmas, self.params)
                if found is not None and found.matched >= self.params.min_points:
                    pose, self.last = found.pose, found
                    c = se3_log(np.linalg.inv(prediction) @ pose)
                    self._corrections.append((float(c[:3] @ c[:3] / 3), float(c[3:] @ c[3:] / 3)))
        self._poses.append(pose)
        self._guesses.append(guess)
        self.map.add(points @ pose[:3, :3].T + pose[:3, 3], normals @ pose[:3, :3].T)
        return pose
