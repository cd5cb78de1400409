"""Where a session's surface is, from its stored ToF clouds: each cloud read once
(:func:`processing.surface_evidence.surface_evidence`), kept per cell of the robot's frame,
and placed in the world by the cloud's odometry pose corrected as the frame nearest in time
was (mosaic or live map), so clouds and frames agree on where the plate's edges are."""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from sqlalchemy import select
from sqlalchemy.orm import Session

from processing.coverage import SurfaceVotes
from processing.poses import compose_se2, rot2
from processing.surface_evidence import pixel_rays, surface_evidence
from robot_link.clouds import decode_cloud
from robot_link.protocol import ProtocolError
from server.storage.files import SessionFiles
from server.storage.models import Cloud

MAX_CELLS = 4_000_000  # cells kept over all cached clouds (8 bytes each)


@dataclass(frozen=True)
class CloudCells:
    """One cloud's evidence per cell of the robot's frame: cell centres (N, 2) metres and
    the weight for the surface less the weight against it (N,)."""

    xy: NDArray[np.float32]
    net: NDArray[np.float32]


class SurfaceCache:
    """Clouds' evidence by (session, seq, cell size), least recently used dropped beyond a
    bound on the cells kept."""

    def __init__(self, limit: int = MAX_CELLS) -> None:
        self.limit = limit
        self._items: OrderedDict[tuple[str, int, float], CloudCells | None] = OrderedDict()
        self._cells = 0
        self._lock = threading.Lock()

    def get(
        self, files: SessionFiles, cloud: Cloud, T_robot_tof: NDArray[np.float64], cell_m: float
    ) -> CloudCells | None:
        key = (cloud.session_id, cloud.seq, cell_m)
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        cells = _read(files, cloud, T_robot_tof, cell_m)
        with self._lock:
            if key not in self._items:
                self._items[key] = cells
                self._cells += len(cells.net) if cells is not None else 0
            while self._cells > self.limit and len(self._items) > 1:
                _, old = self._items.popitem(last=False)
                self._cells -= len(old.net) if old is not None else 0
        return cells


def _read(
    files: SessionFiles, cloud: Cloud, T_robot_tof: NDArray[np.float64], cell_m: float
) -> CloudCells | None:
    meta: dict[str, Any] = {
        **(cloud.intrinsics or {}),
        "encoding": cloud.encoding,
        "width": cloud.width,
        "height": cloud.height,
    }
    try:
        points = decode_cloud(files.payload(cloud), meta)
    except (OSError, ValueError, KeyError, ProtocolError):
        return None
    intr = [meta.get(k) for k in ("fx", "fy", "cx", "cy")]
    if all(isinstance(v, int | float) and v for v in intr[:2]) and None not in intr:
        grid = points.reshape(cloud.height, cloud.width, 3)
        rays = pixel_rays(cloud.width, cloud.height, *(float(v) for v in intr))  # type: ignore[arg-type]
        ev = surface_evidence(grid, T_robot_tof, rays)
    else:
        ev = surface_evidence(points, T_robot_tof)
    if not len(ev.on):
        return CloudCells(np.zeros((0, 2), np.float32), np.zeros(0, np.float32))
    c = np.floor(ev.xy / cell_m).astype(np.int64)
    keys, inverse = np.unique(c, axis=0, return_inverse=True)
    net = np.bincount(inverse.ravel(), np.where(ev.on, ev.weight, -ev.weight), len(keys))
    return CloudCells(((keys + 0.5) * cell_m).astype(np.float32), net.astype(np.float32))


def session_surface_votes(
    db: Session,
    files: SessionFiles,
    cache: SurfaceCache,
    session_id: str,
    T_robot_tof: NDArray[np.float64],
    cell_m: float,
    frame_times: NDArray[np.float64],
    frame_corrections: NDArray[np.float64],
) -> SurfaceVotes | None:
    """The session's clouds' evidence about its surface in the world frame, each cloud
    placed by its odometry pose corrected by ``frame_corrections`` (F, 3: the world
    correction of the frame at each of ``frame_times`` (F,)), the nearest in time; None
    when no cloud says anything."""
    order = np.argsort(frame_times, kind="stable")
    frame_times, frame_corrections = frame_times[order], frame_corrections[order]
    clouds = db.scalars(
        select(Cloud)
        .where(Cloud.session_id == session_id, Cloud.pose_x.is_not(None))
        .order_by(Cloud.seq)
    )
    parts_xy, parts_net = [], []
    for cloud in clouds:
        cells = cache.get(files, cloud, T_robot_tof, cell_m)
        if cells is None or not len(cells.net):
            continue
        robot = np.array([cloud.pose_x, cloud.pose_y, cloud.pose_yaw or 0.0])
        if len(frame_times):
            k = int(np.searchsorted(frame_times, cloud.timestamp))
            if k == len(frame_times) or (
                k > 0 and cloud.timestamp - frame_times[k - 1] < frame_times[k] - cloud.timestamp
            ):
                k -= 1
            robot = compose_se2(frame_corrections[k], robot)
        parts_xy.append(cells.xy @ rot2(float(robot[2])).T + robot[:2])
        parts_net.append(cells.net)
    if not parts_xy:
        return None
    net = np.concatenate(parts_net)
    return SurfaceVotes(np.vstack(parts_xy), net > 0, np.abs(net))
