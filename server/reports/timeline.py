"""A session's timeline: every moment a reviewer can scrub to, with one answer per moment.

Each camera frame is a moment: its time, where the robot and its camera's footprint were
(by the best registration there is, the same placement the coverage map uses, so the
frame, the coverage map, the mosaic cursor and the 3D view agree), and the defects first
seen then. The telemetry comes as series of any numeric field the robot sent, in the
units its keys name (:mod:`robot_link.telemetry_fields`), on the same clock.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from processing.coverage import footprint
from processing.poses import compose_se2, relative_se2
from robot_link.telemetry_fields import field_unit, numeric_fields
from server.reports.coverage import camera_pose, mosaic_cameras
from server.storage.files import SessionFiles
from server.storage.models import Defect, Frame, InspectionSession, TelemetrySample

FIELD_SCAN = 50  # samples read in each of FIELD_RUNS runs to list a session's telemetry fields
FIELD_RUNS = 8
INSIDE_BLOCK = 256  # footprints tested against every defect at once (bounds the memory)


def inside_convex(points: NDArray[np.floating], polys: NDArray[np.floating]) -> NDArray[np.bool_]:
    """Whether each point lies in each convex polygon: (N, M) for ``points`` (M, 2) and
    ``polys`` (N, K, 2) with corners in order (either direction); the border counts."""
    polys = np.asarray(polys, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    edges = np.roll(polys, -1, axis=1) - polys  # (N, K, 2)
    rel = points[None, :, None, :] - polys[:, None, :, :]  # (N, M, K, 2)
    cross = edges[:, None, :, 0] * rel[..., 1] - edges[:, None, :, 1] * rel[..., 0]
    return np.asarray((cross >= 0).all(axis=2) | (cross <= 0).all(axis=2))


def first_sightings(
    centres: NDArray[np.floating], footprints: NDArray[np.floating]
) -> NDArray[np.int64]:
    """For each point (M, 2), the index of the first footprint (N, 4, 2) holding it, -1
    when none does."""
    first = np.full(len(centres), -1, dtype=np.int64)
    for lo in range(0, len(footprints), INSIDE_BLOCK):
        todo = np.flatnonzero(first < 0)
        if not len(todo):
            break
        hit = inside_convex(centres[todo], footprints[lo : lo + INSIDE_BLOCK])
        seen = hit.any(axis=0)
        first[todo[seen]] = lo + hit[:, seen].argmax(axis=0)
    return first


def session_timeline(
    db: Session,
    files: SessionFiles,
    session_id: str,
    *,
    corrections: NDArray[np.float64] | None = None,
) -> dict[str, Any]:
    """The session's moments (one per camera frame, in capture order) as JSON: time since
    the session's first record, the robot's pose and the camera's footprint (world metres,
    placed as :func:`server.reports.coverage.session_coverage` places them), the defects
    with the frame they were first seen in, and the telemetry fields there are to plot."""
    s = db.get(InspectionSession, session_id)
    camera = (s.calibration or {}).get("camera", {}) if s is not None else {}
    px_per_m = float(camera.get("px_per_m") or 0) or None
    T_rc = np.asarray(camera.get("T_robot_camera", [0.0, 0.0, 0.0]), dtype=np.float64)
    T_cr = relative_se2(T_rc, np.zeros(3))  # the robot seen from its camera
    frames = list(
        db.scalars(select(Frame).where(Frame.session_id == session_id).order_by(Frame.seq))
    )
    first_t = [f.timestamp for f in frames[:1]]
    t0 = db.scalar(
        select(TelemetrySample.timestamp)
        .where(TelemetrySample.session_id == session_id)
        .order_by(TelemetrySample.timestamp)
    )
    start = min(first_t + ([t0] if t0 is not None else []), default=0.0)
    mosaic = mosaic_cameras(files, session_id)
    moments: list[dict[str, Any]] = []
    polys: list[NDArray[np.float64]] = []
    owners: list[int] = []  # moment index of each footprint
    for i, f in enumerate(frames):
        moment: dict[str, Any] = {"seq": f.seq, "t_s": round(f.timestamp - start, 4)}
        if f.pose_x is not None:
            cam, by = camera_pose(f, mosaic, corrections, T_rc)
            robot = compose_se2(cam, T_cr)
            moment.update(robot=[round(float(v), 5) for v in robot], placed_by=by)
            if px_per_m:
                poly = footprint(cam, px_per_m, (f.width, f.height))
                moment["footprint"] = poly.round(4).tolist()
                polys.append(poly)
                owners.append(i)
        moments.append(moment)
    return {
        "session_id": session_id,
        "start": start,
        "duration_s": round(max((m["t_s"] for m in moments), default=0.0), 4),
        "frames": moments,
        "defects": _defect_moments(db, session_id, moments, polys, owners),
        "telemetry": telemetry_fields(db, session_id),
    }


def _defect_moments(
    db: Session,
    session_id: str,
    moments: list[dict[str, Any]],
    polys: list[NDArray[np.float64]],
    owners: list[int],
) -> list[dict[str, Any]]:
    """Each defect with the moment it was first seen: a frame defect in its own frame, a
    defect placed on the structure in the first footprint holding its centre."""
    defects = list(
        db.scalars(select(Defect).where(Defect.session_id == session_id).order_by(Defect.id))
    )
    by_seq = {m["seq"]: i for i, m in enumerate(moments)}
    placed = [
        d
        for d in defects
        if d.source != "frame" and d.world_x_m is not None and d.world_y_m is not None
    ]
    first: dict[int, int] = {}
    if placed and polys:
        centres = np.array(
            [
                [d.world_x_m + (d.world_w_m or 0.0) / 2, d.world_y_m + (d.world_h_m or 0.0) / 2]
                for d in placed
            ]
        )
        hits = first_sightings(centres, np.stack(polys))
        first = {d.id: owners[int(k)] for d, k in zip(placed, hits) if k >= 0}
    out = []
    for d in defects:
        i = by_seq.get(d.frame_seq) if d.source == "frame" else first.get(d.id)
        out.append(
            {
                "id": d.id,
                "number": d.number,
                "source": d.source,
                "defect_class": d.defect_class,
                "review_status": d.review_status,
                "first_seq": None if i is None else moments[i]["seq"],
                "t_s": None if i is None else moments[i]["t_s"],
            }
        )
    return out


def telemetry_fields(db: Session, session_id: str) -> dict[str, Any]:
    """The numeric telemetry fields a session holds (read from runs of samples spread over
    it) with their units, and whether it holds any."""
    base = select(TelemetrySample.data).where(TelemetrySample.session_id == session_id)
    count = db.scalar(
        select(func.count())
        .select_from(TelemetrySample)
        .where(TelemetrySample.session_id == session_id)
    )
    names: dict[str, None] = {}
    # runs of samples spread over the session: a field a robot sends only for a while (a
    # sweep's progress) is found wherever it was sent
    for start in np.linspace(0, max(0, (count or 0) - FIELD_SCAN), FIELD_RUNS).astype(int):
        runs = base.order_by(TelemetrySample.seq).offset(int(start)).limit(FIELD_SCAN)
        for data in db.scalars(runs):
            for name in numeric_fields(data if isinstance(data, dict) else {}):
                names.setdefault(name)
    return {
        "any": bool(count),
        "fields": [{"name": n, "unit": field_unit(n)} for n in names],
    }


def telemetry_series(
    db: Session, session_id: str, fields: Sequence[str], max_points: int
) -> dict[str, Any]:
    """The named fields over the whole session: sample times (robot clock) and one value
    per sample and field (None where a sample lacks it), every k-th sample when there are
    more than ``max_points``."""
    rows = db.execute(
        select(TelemetrySample.timestamp, TelemetrySample.data)
        .where(TelemetrySample.session_id == session_id)
        .order_by(TelemetrySample.timestamp, TelemetrySample.seq)
    ).all()
    stride = max(1, -(-len(rows) // max(1, max_points)))
    kept = rows[::stride]
    series: dict[str, list[float | None]] = {name: [] for name in fields}
    for _, data in kept:
        values = numeric_fields(data if isinstance(data, dict) else {})
        for name in fields:
            series[name].append(values.get(name))
    return {
        "samples": len(rows),
        "stride": stride,
        "timestamps": [t for t, _ in kept],
        "series": series,
        "units": {name: field_unit(name) for name in fields},
    }
