"""The 3D map growing live while the robot inspects: every ToF cloud the station stores is
also added to :class:`processing.mapping.IncrementalMap` (the same pose graph as the
``map`` job's, optimised every ``OPTIMISE_EVERY`` clouds and at each loop closure) in a
worker process (ICP would starve the viser server and the event loop in this one), and the
map so far is shown in the 3D view. The ``map`` job still builds the final map from every
cloud after the session (the live view skips clouds when its worker falls behind).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from numpy.typing import NDArray

from server.live.worker import LiveWorker

log = logging.getLogger(__name__)
MAX_PENDING = 3  # clouds waiting for the worker; beyond, the live view skips (the job uses all)
DISPLAY_POINTS = 150_000
OPTIMISE_EVERY = 10

_maps: dict[str, Any] = {}  # in the worker process: session id -> IncrementalMap


def _place(
    session_id: str, payload: bytes, meta: dict[str, Any], guess: NDArray[np.float64]
) -> tuple[int, NDArray[np.float32], NDArray[np.float32]]:
    """In the worker: decode one cloud, add it to its session's map; (clouds, map points,
    sensor positions)."""
    from processing.mapping import IncrementalMap, MapParams
    from robot_link.clouds import decode_cloud
    from server.live.scene3d import display_points

    points = decode_cloud(payload, meta)
    live = _maps.get(session_id)
    if live is None:
        _maps.clear()  # one live session at a time: a new one replaces the old
        live = _maps[session_id] = IncrementalMap(MapParams(), optimise_every=OPTIMISE_EVERY)
    live.add(points, guess, shape=(meta["height"], meta["width"]))
    poses = live.poses
    return (
        len(poses),
        display_points(live.points, DISPLAY_POINTS),
        poses[:, :3, 3].astype(np.float32),
    )


class LiveMap:
    """Feeds stored clouds to the worker and their map to the 3D view."""

    def __init__(self, factory: Any, scene: Any) -> None:
        self.factory = factory
        self.scene = scene
        self.worker = LiveWorker("live map", MAX_PENDING)
        self._mounts: dict[str, NDArray[np.float64] | None] = {}

    @property
    def skipped(self) -> int:
        """Clouds the live map skipped because its worker was behind."""
        return self.worker.skipped

    def _mount(self, session_id: str) -> NDArray[np.float64] | None:
        """T_robot_tof of a session's calibration (looked up once)."""
        if session_id not in self._mounts:
            from server.storage.models import InspectionSession

            with self.factory() as db:
                s = db.get(InspectionSession, session_id)
                T = (
                    (s.calibration or {}).get("tof", {}).get("T_robot_tof")
                    if s is not None
                    else None
                )
            self._mounts[session_id] = np.asarray(T, dtype=np.float64) if T is not None else None
        return self._mounts[session_id]

    def offer(self, session_id: str, payload: bytes, meta: dict[str, Any]) -> bool:
        """Queue one stored cloud for the live map; False when it is skipped (no odometry
        pose or mount, or the worker is behind)."""
        from processing.poses import se2_to_se3

        pose, mount = meta.get("pose"), self._mount(session_id)
        if not isinstance(pose, dict) or mount is None:
            return False
        guess = se2_to_se3(float(pose["x"]), float(pose["y"]), float(pose["yaw"])) @ mount

        def show(placed: tuple[int, NDArray[np.float32], NDArray[np.float32]]) -> None:
            clouds, points, trajectory = placed
            self.scene.show_live_map(session_id, points, clouds, trajectory)

        return self.worker.submit(_place, session_id, payload, dict(meta), guess, done=show)

    def close(self) -> None:
        """Stop the worker."""
        self.worker.close()
