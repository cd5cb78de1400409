"""Inspection sessions: list, read, their frames, telemetry, defects and result files."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query
from fastapi.responses import FileResponse
from sqlalchemy import func, select

from server.deps import SessionDep, StateDep, get_current_user
from server.errors import NotFound
from server.models import Cloud, Defect, Frame, InspectionSession, Job, TelemetrySample
from server.schemas import (
    DefectsPublic,
    FramesPublic,
    JobPublic,
    SessionPublic,
    SessionsPublic,
    TelemetryListPublic,
)

router = APIRouter(prefix="/api/sessions", tags=["sessions"], dependencies=[Depends(get_current_user)])

MAX_INT = 2**63 - 1  # SQLite's largest integer: a bigger id cannot exist
RESULT_FILES = {
    "mosaic.png": "image/png",
    "mosaic_overview.png": "image/png",
    "mosaic_coverage.png": "image/png",
    "mosaic.json": "application/json",
    "mosaic.dzi": "application/xml",
    "map.ply": "application/octet-stream",
    "trajectory.tum": "text/plain",
    "crack_mask.png": "image/png",
    "corrosion_mask.png": "image/png",
}


def _count(db: SessionDep, model: Any, session_id: str) -> int:
    return db.scalar(select(func.count()).select_from(model).where(model.session_id == session_id)) or 0


def _public(db: SessionDep, s: InspectionSession, *, with_jobs: bool = True) -> SessionPublic:
    out = SessionPublic.model_validate(s)
    out.frames = _count(db, Frame, s.id)
    out.clouds = _count(db, Cloud, s.id)
    out.telemetry = _count(db, TelemetrySample, s.id)
    out.defects = db.scalar(select(func.count()).select_from(Defect).where(Defect.session_id == s.id, Defect.source == "mosaic")) or 0
    out.frame_defects = db.scalar(select(func.count()).select_from(Defect).where(Defect.session_id == s.id, Defect.source == "frame")) or 0
    out.robot_name = s.robot.name if s.robot else None
    if with_jobs:
        jobs = db.scalars(select(Job).where(Job.session_id == s.id).order_by(Job.id))
        out.jobs = [JobPublic.model_validate(j) for j in jobs]
    return out


def get_session_or_404(db: SessionDep, session_id: str) -> InspectionSession:
    """The session, or NotFound."""
    s = db.get(InspectionSession, session_id)
    if s is None:
        raise NotFound(f"session {session_id} not found")
    return s


@router.get("", response_model=SessionsPublic)
def read_sessions(db: SessionDep, skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0, limit: Annotated[int, Query(ge=1, le=500)] = 100) -> SessionsPublic:
    """List inspection sessions, newest first."""
    count = db.scalar(select(func.count()).select_from(InspectionSession)) or 0
    rows = db.scalars(select(InspectionSession).order_by(InspectionSession.started_at.desc()).offset(skip).limit(limit))
    return SessionsPublic(data=[_public(db, s) for s in rows], count=count)


@router.get("/{session_id}", response_model=SessionPublic)
def read_session(db: SessionDep, session_id: str) -> SessionPublic:
    """One session with counts of what it stored and its jobs."""
    return _public(db, get_session_or_404(db, session_id))


@router.get("/{session_id}/frames", response_model=FramesPublic)
def read_frames(db: SessionDep, session_id: str, skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0, limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> FramesPublic:
    """Camera frames of a session in sequence order."""
    get_session_or_404(db, session_id)
    rows = db.scalars(select(Frame).where(Frame.session_id == session_id).order_by(Frame.seq).offset(skip).limit(limit))
    return FramesPublic(data=list(rows), count=_count(db, Frame, session_id))  # type: ignore[arg-type]


@router.get("/{session_id}/frames/{seq}/image", response_class=FileResponse)
def read_frame_image(db: SessionDep, state: StateDep, session_id: str, seq: Annotated[int, Path(ge=0, le=MAX_INT)]) -> FileResponse:
    """The JPEG of one frame."""
    frame = db.scalar(select(Frame).where(Frame.session_id == session_id, Frame.seq == seq))
    if frame is None:
        raise NotFound(f"frame {seq} of session {session_id} not found")
    return FileResponse(state.files.resolve(frame.path), media_type="image/jpeg")


@router.get("/{session_id}/telemetry", response_model=TelemetryListPublic)
def read_telemetry(db: SessionDep, session_id: str, skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0, limit: Annotated[int, Query(ge=1, le=5000)] = 500) -> TelemetryListPublic:
    """Telemetry samples of a session in sequence order."""
    get_session_or_404(db, session_id)
    rows = db.scalars(select(TelemetrySample).where(TelemetrySample.session_id == session_id).order_by(TelemetrySample.seq).offset(skip).limit(limit))
    return TelemetryListPublic(data=list(rows), count=_count(db, TelemetrySample, session_id))  # type: ignore[arg-type]


@router.get("/{session_id}/defects", response_model=DefectsPublic)
def read_defects(db: SessionDep, session_id: str, defect_class: str | None = None,
                 source: Annotated[str | None, Query(pattern="^(mosaic|frame)$")] = None, skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0, limit: Annotated[int, Query(ge=1, le=5000)] = 1000) -> DefectsPublic:
    """Defects found in a session, optionally of one class or one source (mosaic or frame)."""
    get_session_or_404(db, session_id)
    q = select(Defect).where(Defect.session_id == session_id)
    if defect_class:
        q = q.where(Defect.defect_class == defect_class)
    if source:
        q = q.where(Defect.source == source)
    count = db.scalar(select(func.count()).select_from(q.subquery())) or 0
    rows = db.scalars(q.order_by(Defect.id).offset(skip).limit(limit))
    return DefectsPublic(data=list(rows), count=count)  # type: ignore[arg-type]


@router.get("/{session_id}/results/{name}", response_class=FileResponse)
def read_result_file(db: SessionDep, state: StateDep, session_id: str, name: str) -> FileResponse:
    """A processing result file (mosaic.png, mosaic_overview.png, map.ply, trajectory.tum, masks)."""
    get_session_or_404(db, session_id)
    if name not in RESULT_FILES:
        raise NotFound(f"no result file named {name!r}; known: {sorted(RESULT_FILES)}")
    path = state.files.results_dir(session_id) / name
    if not path.is_file():
        raise NotFound(f"{name} of session {session_id} does not exist yet")
    return FileResponse(path, media_type=RESULT_FILES[name], filename=name)


@router.get("/{session_id}/mosaic_files/{level}/{col}_{row}.jpg", response_class=FileResponse)
def read_mosaic_tile(db: SessionDep, state: StateDep, session_id: str, level: Annotated[int, Path(ge=0, le=64)],
                     col: Annotated[int, Path(ge=0, le=MAX_INT)], row: Annotated[int, Path(ge=0, le=MAX_INT)]) -> FileResponse:
    """One tile of the mosaic's Deep Zoom pyramid (``results/mosaic.dzi`` describes it)."""
    get_session_or_404(db, session_id)
    path = state.files.results_dir(session_id) / "mosaic_files" / str(level) / f"{col}_{row}.jpg"
    if not path.is_file():
        raise NotFound(f"no tile {level}/{col}_{row} in the mosaic of session {session_id}")
    return FileResponse(path, media_type="image/jpeg", headers={"Cache-Control": "private, max-age=3600"})


@router.get("/{session_id}/report.json")
def read_report_json(db: SessionDep, session_id: str) -> dict[str, Any]:
    """Session summary with jobs, processing results and every defect."""
    s = _public(db, get_session_or_404(db, session_id))
    defects = read_defects(db, session_id, source=None, limit=5000)
    results = {j.kind: j.result for j in s.jobs if j.state == "done"}
    return {
        "session": s.model_dump(mode="json", exclude={"jobs"}),
        "jobs": [j.model_dump(mode="json", exclude={"result"}) for j in s.jobs],
        "results": results,
        "defects": [d.model_dump(mode="json") for d in defects.data],
        "missing": [k for k in ("stitch", "map", "detect") if k not in results],
    }
