"""Earlier visits of a structure on record for the processed inspection (the shared
``inspected`` session): each one's mosaic overview and defects are the session's moved by
a known offset (its robot started elsewhere on the structure), one crack shorter, one
defect not yet there, one since repaired. Tests that add them take them away again."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

import cv2
import httpx
import numpy as np

from server.storage.db import make_engine, make_sessionmaker
from server.storage.files import SessionFiles
from server.storage.models import Defect, InspectionSession, Job, JobState, SessionStatus
from tests.conftest import LiveServer

REPAIRED_NUMBER = 999  # the number of the defect repaired since the earlier visit


@dataclass(frozen=True)
class EarlierVisit:
    """What an earlier visit holds against the session it was made from."""

    id: str
    started_at: datetime
    shift_m: tuple[float, float]  # its world frame's offset from the session's
    grown_id: int  # the session's crack that is shorter on the earlier visit
    missing_id: int | None  # the session's defect the earlier visit lacks
    repaired: bool  # whether it has a defect (number REPAIRED_NUMBER) the session lacks
    found: int  # the session's defects it was made from (mosaic, not rejected)


def stitch_result(live: LiveServer, sid: str) -> dict:
    """The session's stitch job result."""
    jobs = httpx.get(f"{live.url}/api/sessions/{sid}/jobs").json()
    return next(j for j in jobs if j["kind"] == "stitch")["result"]


def add_earlier_visit(
    live: LiveServer,
    sid: str,
    structure_id: int,
    *,
    days: int = 730,
    shift_m: tuple[float, float] = (0.03, -0.02),
    shorter_mm: float = 8.0,
    missing: bool = True,
    repaired: bool = True,
) -> EarlierVisit:
    """A visit of ``structure_id`` ``days`` before session ``sid``, its robot started
    about ``shift_m`` off (whole overview pixels; its 3D map moved alike where the session
    has one): the session's first crack
    ``shorter_mm`` shorter, with or without the session's next defect (``missing``) and
    a defect repaired since (``repaired``, at 1.5, 0.8 m)."""
    stitch = stitch_result(live, sid)
    k = stitch["px_per_m"] * stitch["overview_scale"]  # overview pixels per metre
    shift_px = (round(shift_m[0] * k), round(shift_m[1] * k))
    shift = (shift_px[0] / k, shift_px[1] / k)
    files = SessionFiles(live.settings.data_dir)
    earlier_id = f"earlier{days}-{sid[:20]}"
    overview = cv2.imread(str(files.results_dir(sid) / "mosaic_overview.png"))
    assert overview is not None
    M = np.float32([[1, 0, shift_px[0]], [0, 1, shift_px[1]]])
    moved = cv2.warpAffine(overview, M, overview.shape[1::-1], borderMode=cv2.BORDER_REFLECT)
    files.results_dir(earlier_id).mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(files.results_dir(earlier_id) / "mosaic_overview.png"), moved)
    mapped = _moved_map(files, sid, earlier_id, shift)
    engine = make_engine(live.settings.resolved_database_url())
    try:
        with make_sessionmaker(engine)() as db:
            now = db.get(InspectionSession, sid)
            assert now is not None
            earlier = InspectionSession(
                id=earlier_id,
                structure="the same girder",
                structure_id=structure_id,
                datum={"x": 0.0, "y": 0.0, "yaw": 0.0},
                operator="earlier team",
                status=SessionStatus.ended,
                started_at=now.started_at - timedelta(days=days),
            )
            db.add(earlier)
            db.add(
                Job(
                    session_id=earlier_id,
                    kind="stitch",
                    state=JobState.done,
                    result={**stitch, "overview_path": "mosaic_overview.png"},
                )
            )
            if mapped:
                db.add(Job(session_id=earlier_id, kind="map", state=JobState.done, result={}))
            found = list(
                db.query(Defect).filter_by(session_id=sid, source="mosaic").order_by(Defect.number)
            )
            found = [d for d in found if d.review_status != "rejected"]
            cracks = [d for d in found if d.defect_class == "crack"]
            assert cracks and len(found) >= 2
            grown, after = cracks[0], next(d for d in found if d is not cracks[0])
            columns = [
                c.key
                for c in Defect.__table__.columns
                if c.key not in ("id", "session_id", "job_id")
            ]
            for d in found:
                if missing and d is after:
                    continue
                copy = Defect(session_id=earlier_id, **{c: getattr(d, c) for c in columns})
                copy.world_x_m = (d.world_x_m or 0.0) + shift[0]
                copy.world_y_m = (d.world_y_m or 0.0) + shift[1]
                if d is grown:
                    copy.length_mm = (d.length_mm or 0.0) - shorter_mm
                db.add(copy)
            if repaired:
                gone = Defect(session_id=earlier_id, **{k: getattr(grown, k) for k in columns})
                gone.world_x_m, gone.world_y_m, gone.number = 1.5, 0.8, REPAIRED_NUMBER
                db.add(gone)
            db.commit()
            return EarlierVisit(
                earlier_id,
                earlier.started_at,
                shift,
                grown.id,
                after.id if missing else None,
                repaired,
                len(found),
            )
    finally:
        engine.dispose()


def _moved_map(files: SessionFiles, sid: str, earlier_id: str, shift: tuple[float, float]) -> bool:
    """The session's 3D map moved by the earlier world's offset, as the earlier visit's
    (False when the session has none)."""
    import open3d as o3d

    path = files.results_dir(sid) / "map.ply"
    if not path.exists():
        return False
    pcd = o3d.io.read_point_cloud(str(path))
    pcd.translate((shift[0], shift[1], 0.0))
    return bool(o3d.io.write_point_cloud(str(files.results_dir(earlier_id) / "map.ply"), pcd))


def forget_session(live: LiveServer, session_id: str) -> None:
    """Remove a session added behind the station's back, with its defects and jobs."""
    from sqlalchemy import text

    engine = make_engine(live.settings.resolved_database_url())
    try:
        with engine.begin() as conn:
            for table in ("defects", "jobs", "inspection_sessions"):
                column = "id" if table == "inspection_sessions" else "session_id"
                conn.execute(text(f"DELETE FROM {table} WHERE {column} = :s"), {"s": session_id})
    finally:
        engine.dispose()
