"""The 3D map growing live while the robot inspects: every ToF cloud the station stores is
also added to :class:`processing.mapping.IncrementalMap` (the same pose graph as the
``map`` job's, optimised after every cloud while the graph is small, after every tenth of
the clouds so far once it grows, and at each loop closure) in a worker process (ICP would
starve the viser server and the event loop in this one), with the downward camera's steps
between the clouds as its frames arrive (:mod:`server.live.live_camera`), and the map so
far is shown in the 3D view. The ``map`` job still builds the final map from every
cloud after the session (the live view skips clouds when its worker falls behind).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from numpy.typing import NDArray

from server.live.worker import LiveWorker

log = logging.getLogger(__name__)
# clouds and frames waiting for the worker; beyond, the live view skips (the job uses all)
MAX_PENDING = 6
DISPLAY_POINTS = 150_000
# between optimisations each cloud is chained to the one before it, and a turn's step can
# leave the chain centimetres worse than the odometry until the next one (the pose graph's
# odometry edges and plane landmarks pull it back): the live map asks for an optimisation
# after every cloud, which the graph spaces out to a tenth of its clouds as it grows
# (processing.mapping.incremental)
OPTIMISE_EVERY = 1

_maps: dict[str, Any] = {}  # in the worker process: session id -> IncrementalMap
_odometry: dict[str, list[tuple[float, NDArray[np.float64]]]] = {}  # (time, odometry pose)
_chains: dict[str, Any] = {}  # session id -> its frames' chain (server.live.live_camera)
# session id -> each cloud's start for ICP: chained from the camera's steps where known
_guided: dict[str, list[NDArray[np.float64]]] = {}


def _chain(session_id: str, calibration: dict[str, Any], T_robot_tof: NDArray[np.float64]) -> Any:
    """In the worker: the session's frame chain (one live session at a time)."""
    from server.live.live_camera import FrameChain

    if session_id not in _chains:
        _chains.clear()
        _chains[session_id] = FrameChain(calibration, T_robot_tof)
    return _chains[session_id]


def _add_camera_edges(session_id: str) -> None:
    """In the worker: the camera edges whose frames have arrived, into the session's graph
    (optimised with the next cloud)."""
    from open3d.pipelines.registration import PoseGraphEdge

    live, chain = _maps.get(session_id), _chains.get(session_id)
    if live is None or chain is None:
        return
    for source, target, T, information in chain.edges(live.poses):
        live.graph.edges.append(PoseGraphEdge(source, target, T, information, uncertain=False))
    # a lane passed again: robust, as the ToF's loop closures are
    times = np.array([t for t, _ in _odometry.get(session_id, [])], np.float64)
    for source, target, T, information in chain.loops(live.poses, times[: len(live.poses)]):
        live.graph.edges.append(PoseGraphEdge(source, target, T, information, uncertain=True))


def _frame(
    session_id: str,
    payload: bytes,
    pose: NDArray[np.float64],
    t: float,
    calibration: dict[str, Any],
    T_robot_tof: NDArray[np.float64],
    follows: bool,
) -> None:
    """In the worker: one stored frame (JPEG/PNG bytes) taken at ``t`` with the robot at
    odometry ``pose`` (x, y, yaw) into the session's frame chain (``follows``: no frame
    skipped since the last)."""
    import cv2

    image = cv2.imdecode(np.frombuffer(payload, np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None:
        return
    _chain(session_id, calibration, T_robot_tof).add(image, t, pose, follows, payload)
    _add_camera_edges(session_id)


def _place(
    session_id: str,
    payload: bytes,
    meta: dict[str, Any],
    guess: NDArray[np.float64],
    t: float,
) -> tuple[int, NDArray[np.float32], NDArray[np.float32], NDArray[np.float64]]:
    """In the worker: decode one cloud, add it to its session's map; (clouds, map points,
    sensor positions, corrections): each cloud's time (robot clock) and the planar
    correction (dx, dy, dyaw) that takes its odometry pose to where the map placed it."""
    from processing.mapping import IncrementalMap, MapParams, TrackingParams
    from processing.poses import se2_of_matrix
    from robot_link.clouds import decode_cloud
    from server.live.scene3d import display_points

    points = decode_cloud(payload, meta)
    live = _maps.get(session_id)
    if live is None:
        _maps.clear()  # one live session at a time: a new one replaces the old
        _odometry.clear()
        _guided.clear()
        # as the ``map`` job: the station's dense clouds and wheel odometry suit the
        # pairwise graph (tracking is for sparse sequences with poor odometry)
        params = MapParams(tracking=TrackingParams(enabled=False))
        live = _maps[session_id] = IncrementalMap(params, optimise_every=OPTIMISE_EVERY)
    odometry = _odometry.setdefault(session_id, [])
    guided = _guided.setdefault(session_id, [])
    chain = _chains.get(session_id)
    start = guess
    if odometry:  # ICP from the camera's step where its frames have come, as the job does
        step = None if chain is None else chain.relative(odometry[-1][0], t)
        if step is None:
            step = np.linalg.inv(odometry[-1][1]) @ guess
        start = guided[-1] @ step
    live.add(points, start, shape=(meta["height"], meta["width"]))
    if chain is not None and odometry:  # the camera's step into this cloud, once its frames come
        chain.waiting.append((len(odometry), odometry[-1][0], t))
        _add_camera_edges(session_id)
    odometry.append((t, guess))
    guided.append(start)
    poses = live.poses
    corrections = np.array(
        [
            [t_k, *se2_of_matrix(pose @ np.linalg.inv(odo))]
            for (t_k, odo), pose in zip(odometry, poses)
        ]
    )
    return (
        len(poses),
        display_points(live.points, DISPLAY_POINTS),
        poses[:, :3, 3].astype(np.float32),
        corrections,
    )


def _warm() -> None:
    """In the worker: what placing the first cloud needs, loaded ahead of it."""
    import processing.mapping  # noqa: F401  (Open3D and the pose graph)
    import robot_link.clouds  # noqa: F401
    import server.live.scene3d  # noqa: F401


class LiveMap:
    """Feeds stored clouds to the worker and their map to the 3D view."""

    def __init__(self, factory: Any, scene: Any) -> None:
        self.factory = factory
        self.scene = scene
        self.worker = LiveWorker("live map", MAX_PENDING)
        # session id -> (N, 4): time and the planar correction of each mapped cloud's
        # odometry pose (the coverage map places frames with it)
        self.corrections: dict[str, NDArray[np.float64]] = {}
        self._calibrations: dict[str, dict[str, Any]] = {}
        self._skipped_clouds = 0
        self._frame_gaps: set[str] = set()  # sessions whose last frame the worker skipped

    @property
    def skipped(self) -> int:
        """Clouds the live map skipped because its worker was behind."""
        return self._skipped_clouds

    def _calibration(self, session_id: str) -> dict[str, Any]:
        """A session's calibration (looked up once)."""
        if session_id not in self._calibrations:
            from server.storage.models import InspectionSession

            with self.factory() as db:
                s = db.get(InspectionSession, session_id)
                self._calibrations[session_id] = dict(s.calibration or {}) if s else {}
        return self._calibrations[session_id]

    def _mount(self, session_id: str) -> NDArray[np.float64] | None:
        """T_robot_tof of a session's calibration."""
        T = self._calibration(session_id).get("tof", {}).get("T_robot_tof")
        return np.asarray(T, dtype=np.float64) if T is not None else None

    def warm(self) -> None:
        """A session has started: get the worker ready before its first cloud."""
        self.worker.warm(_warm)

    def offer(self, session_id: str, payload: bytes, meta: dict[str, Any], t: float = 0.0) -> bool:
        """Queue one stored cloud (taken at ``t``, robot clock) for the live map; False when
        it is skipped (no odometry pose or mount, or the worker is behind)."""
        from processing.poses import se2_to_se3

        pose, mount = meta.get("pose"), self._mount(session_id)
        if not isinstance(pose, dict) or mount is None:
            return False
        guess = se2_to_se3(float(pose["x"]), float(pose["y"]), float(pose["yaw"])) @ mount

        def show(placed: tuple[int, Any, Any, NDArray[np.float64]]) -> None:
            clouds, points, trajectory, corrections = placed
            self.corrections = {session_id: corrections}  # the live session's only
            self.scene.show_live_map(session_id, points, clouds, trajectory)

        placed = self.worker.submit(_place, session_id, payload, dict(meta), guess, t, done=show)
        self._skipped_clouds += not placed
        return placed

    def offer_frame(
        self, session_id: str, payload: bytes, meta: dict[str, Any], t: float = 0.0
    ) -> bool:
        """Queue one stored frame (taken at ``t``, robot clock) for the live map's camera
        steps; False when it is skipped (no pose, no calibrated camera or ToF mount, or the
        worker is behind)."""
        pose, mount = meta.get("pose"), self._mount(session_id)
        camera = self._calibration(session_id).get("camera", {})
        if not isinstance(pose, dict) or mount is None or not camera.get("px_per_m"):
            return False
        robot = np.array([float(pose["x"]), float(pose["y"]), float(pose["yaw"])])
        follows = session_id not in self._frame_gaps
        taken = self.worker.submit(
            _frame, session_id, payload, robot, t, dict(camera), mount, follows, done=lambda _: None
        )
        if taken:
            self._frame_gaps.discard(session_id)
        else:  # the next frame is not registered to the last one taken
            self._frame_gaps.add(session_id)
        return taken

    def close(self) -> None:
        """Stop the worker."""
        self.worker.close()
