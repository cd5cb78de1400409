"""A session's coverage, from its stored frames: each frame's footprint placed by its pose
(odometry at capture) and the camera calibration, judged by :mod:`processing.coverage`
(resolution, sharpness, exposure), rasterised, holes listed. Frame qualities are cached:
a live session's map is asked for every second or two and only new frames are read."""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from sqlalchemy import select
from sqlalchemy.orm import Session

from processing.coverage import (
    CoverageParams,
    FrameQuality,
    coverage_map,
    dark_tiles,
    footprint,
    frame_quality,
    frame_verdicts,
    hole_mask,
)
from processing.poses import compose_se2, relative_se2
from server.reports.surface_votes import SurfaceCache, session_surface_votes
from server.storage.files import SessionFiles
from server.storage.models import Frame, InspectionSession

MAX_CACHED = 50_000  # frames (about 3 KB each with their tiles)


class QualityCache:
    """Frame qualities by (session, seq), least recently used dropped beyond a bound."""

    def __init__(self, limit: int = MAX_CACHED) -> None:
        self.limit = limit
        self._items: OrderedDict[tuple[str, int], FrameQuality | None] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, files: SessionFiles, frame: Frame) -> FrameQuality | None:
        key = (frame.session_id, frame.seq)
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        quality = _measure(files, frame)
        with self._lock:
            self._items[key] = quality
            while len(self._items) > self.limit:
                self._items.popitem(last=False)
        return quality


def _measure(files: SessionFiles, frame: Frame) -> FrameQuality | None:
    try:
        data = np.frombuffer(files.payload(frame), np.uint8)
    except (OSError, ValueError):
        return None
    gray = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
    return frame_quality(gray) if gray is not None else None


def session_coverage(
    db: Session,
    files: SessionFiles,
    cache: QualityCache,
    session_id: str,
    params: CoverageParams,
    *,
    with_grid: bool = True,
    corrections: NDArray[np.float64] | None = None,
    surface_cache: SurfaceCache | None = None,
) -> dict[str, Any]:
    """The coverage of a session as JSON: frames (footprint corners, verdict), surface and
    imaged areas, holes, and (``with_grid``) the grid as run-length rows for drawing.
    Each frame is placed by the best registration there is: the mosaic's (the stitch job's
    image registration), else ``corrections`` (N, 4: time, dx, dy, dyaw; the live map's
    registration of the odometry, the cloud nearest in time), else its odometry pose. The
    surface in view leaves out what the ToF clouds show is no surface (past the plate's
    edges), each cloud placed as the frame nearest in time (``surface_cache`` keeps what
    each cloud says: a live session's map reads only its new clouds), and what only the
    dark tiles of frames showed (the part of a frame past an edge)."""
    s = db.get(InspectionSession, session_id)
    camera = (s.calibration or {}).get("camera", {}) if s is not None else {}
    px_per_m = float(camera.get("px_per_m") or 0) or None
    T_rc = np.asarray(camera.get("T_robot_camera", [0.0, 0.0, 0.0]), dtype=np.float64)
    frames = _placed_frames(db, session_id)
    mm_per_px = 1000.0 / px_per_m if px_per_m else None
    qualities = [cache.get(files, f) for f in frames]
    verdicts = frame_verdicts(qualities, mm_per_px, params)
    polys, placed_by, fixes = [], [], []
    votes = None
    if px_per_m:
        mosaic = mosaic_cameras(files, session_id)
        for f in frames:
            cam, by = camera_pose(f, mosaic, corrections, T_rc)
            polys.append(footprint(cam, px_per_m, (f.width, f.height)))
            placed_by.append(by)
            odom = compose_se2(np.array([f.pose_x, f.pose_y, f.pose_yaw or 0.0]), T_rc)
            fixes.append(compose_se2(cam, relative_se2(odom, np.zeros(3))))
        tof = (s.calibration or {}).get("tof", {}) if s is not None else {}
        if frames and tof.get("T_robot_tof") is not None:
            short = min(min(f.width, f.height) for f in frames) / px_per_m
            votes = session_surface_votes(
                db,
                files,
                surface_cache if surface_cache is not None else SurfaceCache(),
                session_id,
                np.asarray(tof["T_robot_tof"], dtype=np.float64),
                short / params.cells_per_footprint,
                np.array([f.timestamp for f in frames]),
                np.array(fixes),
            )
    cov = coverage_map(
        polys,
        [not v for v in verdicts],
        params,
        surface_votes=votes,
        dark=[dark_tiles(q, params) for q in qualities] if polys else None,
    )
    out: dict[str, Any] = {
        "required_mm_per_px": params.required_mm_per_px,
        "camera_mm_per_px": mm_per_px,
        "frames": [
            {
                "seq": f.seq,
                "footprint": poly.round(4).tolist(),
                "counts": not verdict,
                "why_not": verdict or None,
                "placed_by": by,
            }
            for f, poly, verdict, by in zip(frames, polys, verdicts, placed_by)
        ],
        "frames_not_counted": sum(1 for v in verdicts if v),
        "area_surface_m2": cov.area_surface_m2,
        "area_imaged_m2": cov.area_imaged_m2,
        "fraction_imaged": cov.fraction,
        "holes": [
            {"x_m": h.x_m, "y_m": h.y_m, "bbox_m": list(h.bbox_m), "area_m2": h.area_m2}
            for h in cov.holes
        ],
    }
    if with_grid:
        out["grid"] = _grid(cov)
    return out


def _grid(cov: Any) -> dict[str, Any]:
    """The coverage grid for drawing: its placement, and the holes as run-length rows."""
    return {
        "origin_m": list(cov.origin_m),
        "cell_m": cov.cell_m,
        "rows": int(cov.surface.shape[0]),
        "cols": int(cov.surface.shape[1]) if cov.surface.ndim == 2 else 0,
        "holes_rle": [_runs(row) for row in hole_mask(cov)],
    }


def _placed_frames(db: Session, session_id: str) -> list[Frame]:
    """The session's frames that carry an odometry pose, in seq order."""
    return list(
        db.scalars(
            select(Frame)
            .where(Frame.session_id == session_id, Frame.pose_x.is_not(None))
            .order_by(Frame.seq)
        )
    )


def camera_pose(
    f: Frame,
    mosaic: dict[int, np.ndarray],
    corrections: NDArray[np.float64] | None,
    T_rc: NDArray[np.float64],
) -> tuple[np.ndarray, str]:
    """Where a frame's camera was (x, y, yaw), by the best registration there is, and which
    that was: the mosaic's, the live map's correction nearest in time, or the odometry."""
    robot = np.array([f.pose_x, f.pose_y, f.pose_yaw or 0.0])
    if f.seq in mosaic:
        return mosaic[f.seq], "mosaic"
    if corrections is not None and len(corrections):
        k = int(np.abs(corrections[:, 0] - f.timestamp).argmin())
        return compose_se2(compose_se2(corrections[k, 1:], robot), T_rc), "live map"
    return compose_se2(robot, T_rc), "odometry"


def mosaic_cameras(files: SessionFiles, session_id: str) -> dict[int, np.ndarray]:
    """Camera poses (x, y, yaw; world) of the frames the stitch job placed with confidence
    on a world-referenced mosaic, by frame seq."""
    try:
        world = json.loads((files.results_dir(session_id) / "mosaic.json").read_text())
    except (OSError, ValueError):
        return {}
    if not world.get("world_referenced"):
        return {}
    (ox, oy), scale = world["origin_m"], float(world["px_per_m"])
    return {
        int(f["frame"]): np.array(
            [ox + f["x"] / scale, oy + f["y"] / scale, np.radians(f["theta_deg"])]
        )
        for f in world.get("frames", [])
        if f.get("confident")
    }


def _runs(row: np.ndarray) -> list[int]:
    """Start and length of each run of True in a row, flattened."""
    padded = np.concatenate([[0], row.astype(np.int8), [0]])
    edges = np.flatnonzero(np.diff(padded))
    return np.column_stack([edges[0::2], edges[1::2] - edges[0::2]]).ravel().tolist()
