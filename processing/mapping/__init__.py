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
:mod:`processing.mapping.planes`) are landmarks with their own graph nodes: every cloud that sees
one is tied to it in the three directions a plane fixes, so heading, tilt and height do
not drift along a lane the way a chain of pairwise registrations does. The odometry
edges' errors are raised to what the data show (:meth:`IncrementalMap.odometry_error_scale`:
its heading steps against ICP's where the structure fixes them), so odometry worse than
configured does not pull the map off. Last, the robot's wheels
(:mod:`processing.mapping.wheels`): a rolling robot does not slide sideways, so once the
trajectory is known well enough to fit where the camera sits on the robot, every step is
held to its arc, which fixes the distance along a member in turns that see nothing across it.
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

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from processing.mapping.camera_motion import CameraFactors, with_scale_error
from processing.mapping.camera_mounting import MountingFit, MountingParams, fit_mounting
from processing.mapping.icp import (
    align,
    constrain_to_observable,
    match,
    mutual_overlap,
    plane_information,
    structure_fitness,
    within_bounds,
)
from processing.mapping.incremental import IncrementalMap
from processing.mapping.motion_prior import MotionPriorParams, bridge_gaps, trajectory_feet
from processing.mapping.pairwise import CloudMeasurement, measure_run
from processing.mapping.params import (
    IcpParams,
    LoopParams,
    MapParams,
    OdometryParams,
    PlaneParams,
    SelectParams,
    TrackingParams,
)
from processing.mapping.result import MapResult
from processing.mapping.selection import clean_cloud, filter_organised, fuse_map, select
from processing.mapping.tracking import Tracker, register_to_map

__all__ = [
    "CloudMeasurement",
    "IcpParams",
    "IncrementalMap",
    "LoopParams",
    "MapParams",
    "MapResult",
    "OdometryParams",
    "PlaneParams",
    "SelectParams",
    "TrackingParams",
    "Tracker",
    "align",
    "clean_cloud",
    "constrain_to_observable",
    "filter_organised",
    "fuse_map",
    "match",
    "measure_run",
    "mutual_overlap",
    "plane_information",
    "register_clouds",
    "register_measured",
    "register_to_map",
    "select",
    "structure_fitness",
    "within_bounds",
]


def register_clouds(
    clouds: Sequence[NDArray[np.floating]],
    initial_poses: NDArray[np.floating] | None = None,
    *,
    params: MapParams = MapParams(),
    shape: tuple[int, int] | None = None,
    progress: Callable[[int], None] | None = None,
    camera: CameraFactors | None = None,
    mounting: MountingParams = MountingParams(),
    motion: MotionPriorParams = MotionPriorParams(),
) -> MapResult:
    """Register clouds (each (K, 3), sensor frame) into one world map.

    Parameters
    ----------
    clouds : sequence of (K, 3) arrays; NaN rows are ignored.
    initial_poses : (N, 4, 4) odometry guesses of T_world_sensor, or None (the first cloud
        is the world frame and motion is estimated from geometry alone).
    shape : (H, W) when the clouds are organised depth images (enables depth filtering).
    progress : called with the number of clouds registered so far, after each one.
    camera : the downward camera's steps between the clouds (:mod:`.camera_motion`), edges
        of the pose graph beside the ToF's.
    mounting : how the camera's stated mounting is checked against the ToF's steps
        (:mod:`.camera_mounting`) and corrected where they show it wrong.
    motion : when the camera's steps either side of a stretch its frames did not register
        are carried over it (:mod:`.motion_prior`).
    """
    n = len(clouds)
    if n == 0:
        raise ValueError("clouds must not be empty")
    guesses: NDArray[np.float64] | None = None
    if initial_poses is not None:
        guesses = np.asarray(initial_poses, dtype=np.float64)
        if guesses.shape != (n, 4, 4):
            raise ValueError(
                f"initial_poses must be ({n}, 4, 4), one per cloud, got {guesses.shape}"
            )
        if not np.isfinite(guesses).all():
            raise ValueError("initial_poses contain NaN or infinite values")
    if not params.refine:
        if guesses is None:
            raise ValueError("refine=False needs initial poses")
        pcds = [select(c, params.select, shape) for c in clouds]
        zeros = np.zeros(n)
        return MapResult(
            guesses.copy(),
            fuse_map(pcds, guesses, params.map_voxel_m),
            zeros,
            zeros,
            np.ones(n, bool),
            np.zeros(n, int),
        )
    gaps = np.zeros(n, bool)  # steps the camera did not see, among those it did
    odometry = guesses
    if camera is not None:
        guesses = camera.guided(guesses, n)
        gaps[1:] = [step is None for step in camera.steps[: n - 1]]
    graph_map = IncrementalMap(params)
    for i, cloud in enumerate(clouds):
        graph_map.add(cloud, None if guesses is None else guesses[i], shape, bool(gaps[i]))
        if progress is not None:
            progress(i + 1)
    if camera is None:
        return _finished(graph_map)
    return _fused(graph_map, camera, odometry, mounting, motion)


def _fused(
    graph_map: IncrementalMap,
    camera: CameraFactors,
    odometry: NDArray[np.float64] | None,
    mounting: MountingParams,
    motion: MotionPriorParams,
) -> MapResult:
    """The map of the clouds in ``graph_map`` with the camera's edges added: its mounting
    checked against the ToF's steps (corrected where wrong), its gaps carried over where
    the ``odometry`` poses (N, 4, 4) agree, optimised."""
    n = len(graph_map.poses)
    # the camera's stated mounting checked against the ToF's steps, corrected where wrong
    fit = _check_mounting(graph_map, camera, mounting) if mounting.enabled else None
    if fit is not None and fit.corrected:
        camera = camera.remounted(fit.xi)
    # stretches the frames did not register, carried over by the steps either side
    camera, predicted = _bridged(camera, odometry, motion)
    linked = np.zeros(n, bool)
    for source, target, T, information in camera.edges(graph_map.poses):
        graph_map.graph.edges.append(
            o3d.pipelines.registration.PoseGraphEdge(
                source, target, T, information, uncertain=False
            )
        )
        linked[source] = True
    carried = np.zeros(n, bool)
    carried[1:] = predicted[: n - 1]
    return replace(
        _finished(graph_map),
        camera_steps=linked & ~carried,
        motion_steps=linked & carried,
        camera_mounting=fit,
    )


def _bridged(
    camera: CameraFactors, odometry: NDArray[np.float64] | None, params: MotionPriorParams
) -> tuple[CameraFactors, NDArray[np.bool_]]:
    """The camera's factors with its gaps carried over (:func:`.motion_prior.bridge_gaps`,
    checked against the ``odometry`` poses (N, 4, 4) where given), and which steps were."""
    steps = list(camera.steps)
    if not params.enabled or all(s is not None for s in steps):
        return camera, np.zeros(len(steps), bool)
    measured = (
        None
        if odometry is None
        else trajectory_feet(odometry, camera.camera.T_tof_camera, camera.distances_m)
    )
    filled, predicted = bridge_gaps(steps, measured, params)
    # interpolated from steps the pixels' scale made, as unsure of their length as those
    filled = [
        with_scale_error(s, camera.scale_sigma) if carried else s
        for s, carried in zip(filled, predicted)
    ]
    return replace(camera, steps=filled), predicted


def _check_mounting(
    graph_map: IncrementalMap, camera: CameraFactors, params: MountingParams
) -> MountingFit | None:
    """The camera's mounting fitted to the steps of the clouds the ToF placed
    (:func:`.camera_mounting.fit_mounting`)."""
    poses = graph_map.poses
    n = len(poses) - 1
    usable = np.array(
        [not c.used_odometry and not c.degenerate_dims for c in graph_map.clouds[1:]], bool
    )
    steps = (list(camera.steps) + [None] * n)[:n]
    return fit_mounting(
        steps,
        np.linalg.inv(poses[:-1]) @ poses[1:],
        camera.distances_m[:n],
        camera.camera.T_tof_camera,
        usable,
        params,
    )


def register_measured(
    measured: Sequence[CloudMeasurement],
    initial_poses: NDArray[np.floating],
    *,
    params: MapParams = MapParams(),
    camera: CameraFactors | None = None,
    mounting: MountingParams = MountingParams(),
    motion: MotionPriorParams = MotionPriorParams(),
) -> MapResult:
    """The map of clouds measured apart in runs (:func:`measure_run`, in order, one per
    cloud) with their odometry poses ``initial_poses`` (N, 4, 4): the graph joined,
    loops closed and optimised as :func:`register_clouds` does (without tracking). With
    ``camera`` the runs must have been measured from the camera-guided poses
    (:meth:`CameraFactors.guided` of ``initial_poses``), as :func:`register_clouds` places
    its clouds, and the camera's edges join the graph as they do there."""
    if len(measured) != len(initial_poses) or not measured:
        raise ValueError(
            f"one odometry pose per measured cloud: {len(measured)} clouds, "
            f"{len(initial_poses)} poses"
        )
    if params.tracking.enabled:
        raise ValueError("clouds measured apart are joined without tracking")
    odometry = np.asarray(initial_poses, dtype=np.float64)
    guesses = odometry if camera is None else camera.guided(odometry, len(measured))
    graph_map = IncrementalMap(params)
    for m, guess in zip(measured, guesses):
        graph_map.attach(m, guess)
    if camera is None:
        return _finished(graph_map)
    return _fused(graph_map, camera, odometry, mounting, motion)


def _finished(graph_map: IncrementalMap) -> MapResult:
    params = graph_map.params
    if graph_map.usable_clouds == 0:  # e.g. clouds in millimetres: every point "beyond" range
        raise ValueError(
            f"no cloud has {params.icp.min_points} or more points within {params.select.max_range_m} m of the sensor "
            "(point clouds must be in metres)"
        )
    return graph_map.result()
