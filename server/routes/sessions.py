"""Inspection sessions: list, read, their frames, telemetry, defects and result files."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, Response
from sqlalchemy import func, select

from server.deps import OperatorUser, SessionDep, StateDep, get_current_user
from server.errors import NotFound
from server.models import Cloud, Defect, Frame, InspectionSession, Job, TelemetrySample, utcnow
from server.schemas import (
    CloudsPublic,
    ConditionState,
    DefectPublic,
    DefectReview,
    DefectsPublic,
    FramesPublic,
    JobPublic,
    ReviewStatus,
    SessionPublic,
    SessionsPublic,
    SessionUpdate,
    TelemetryListPublic,
)
from server.thumbnails import defect_image, encode_jpeg

router = APIRouter(prefix="/api/sessions", tags=["sessions"], dependencies=[Depends(get_current_user)])

MAX_INT = 2**63 - 1  # SQLite's largest integer: a bigger id cannot exist
Seq = Annotated[int, Path(ge=0, le=MAX_INT)]
DEFECT_SORT_KEYS = ("id", "defect_class", "source", "length_mm", "max_width_mm", "area_mm2", "area_px", "length_px",
                    "world_x_m", "world_y_m", "review_status", "condition_state")
DEFECT_SORT = "^-?(" + "|".join(DEFECT_SORT_KEYS) + ")$"
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


@router.patch("/{session_id}", response_model=SessionPublic)
def update_session(db: SessionDep, session_id: str, body: SessionUpdate, _: OperatorUser) -> SessionPublic:
    """Correct a session's structure, location, operator or notes (operator role)."""
    s = get_session_or_404(db, session_id)
    for name, value in body.model_dump(exclude_none=True).items():
        setattr(s, name, value)
    db.commit()
    return _public(db, s)


@router.get("/{session_id}/frames", response_model=FramesPublic)
def read_frames(db: SessionDep, session_id: str, skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0, limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> FramesPublic:
    """Camera frames of a session in sequence order."""
    get_session_or_404(db, session_id)
    rows = db.scalars(select(Frame).where(Frame.session_id == session_id).order_by(Frame.seq).offset(skip).limit(limit))
    return FramesPublic(data=list(rows), count=_count(db, Frame, session_id))  # type: ignore[arg-type]


def _payload(state: StateDep, row: Any, what: str) -> bytes:
    try:
        return state.files.payload(row)
    except (OSError, ValueError) as exc:
        raise NotFound(f"the data of {what} cannot be read: {exc}") from None


@router.get("/{session_id}/frames/{seq}/image", response_class=Response)
def read_frame_image(db: SessionDep, state: StateDep, session_id: str, seq: Seq) -> FileResponse:
    """The JPEG of one frame."""
    frame = db.scalar(select(Frame).where(Frame.session_id == session_id, Frame.seq == seq))
    if frame is None:
        raise NotFound(f"frame {seq} of session {session_id} not found")
    return Response(_payload(state, frame, f"frame {seq} of session {session_id}"), media_type="image/jpeg",
                    headers={"Cache-Control": "private, max-age=3600"})


@router.get("/{session_id}/clouds", response_model=CloudsPublic)
def read_clouds(db: SessionDep, session_id: str, skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0, limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> CloudsPublic:
    """ToF point clouds of a session in sequence order."""
    get_session_or_404(db, session_id)
    rows = db.scalars(select(Cloud).where(Cloud.session_id == session_id).order_by(Cloud.seq).offset(skip).limit(limit))
    return CloudsPublic(data=list(rows), count=_count(db, Cloud, session_id))  # type: ignore[arg-type]


def _cloud_or_404(db: SessionDep, session_id: str, seq: int) -> Cloud:
    cloud = db.scalar(select(Cloud).where(Cloud.session_id == session_id, Cloud.seq == seq))
    if cloud is None:
        raise NotFound(f"cloud {seq} of session {session_id} not found")
    return cloud


@router.get("/{session_id}/clouds/{seq}/raw", response_class=Response)
def read_cloud_raw(db: SessionDep, state: StateDep, session_id: str, seq: Seq) -> Response:
    """A cloud's payload as the robot sent it (16-bit depth PNG in mm, or float32 xyz)."""
    cloud = _cloud_or_404(db, session_id, seq)
    png = cloud.encoding == "png16_depth_mm"
    name = f"cloud-{seq:010d}.{'png' if png else 'xyz'}"
    return Response(_payload(state, cloud, f"cloud {seq} of session {session_id}"), media_type="image/png" if png else "application/octet-stream",
                    headers={"Content-Disposition": f'attachment; filename="{name}"'})


@router.get("/{session_id}/clouds/{seq}/points.ply", response_class=Response)
def read_cloud_ply(db: SessionDep, state: StateDep, session_id: str, seq: Seq) -> Response:
    """A cloud's valid points in the sensor frame (metres) as binary PLY."""
    from robot_link.clouds import decode_cloud
    from server.exports import ply_bytes

    cloud = _cloud_or_404(db, session_id, seq)
    meta = {"encoding": cloud.encoding, "width": cloud.width, "height": cloud.height, **cloud.intrinsics}
    try:
        points = decode_cloud(state.files.payload(cloud), meta)
    except (OSError, ValueError) as exc:
        raise NotFound(f"cloud {seq} of session {session_id} cannot be read: {exc}") from None
    return Response(ply_bytes(points), media_type="application/octet-stream",
                    headers={"Content-Disposition": f'attachment; filename="cloud-{seq:06d}.ply"'})


@router.get("/{session_id}/telemetry", response_model=TelemetryListPublic)
def read_telemetry(db: SessionDep, session_id: str, skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0, limit: Annotated[int, Query(ge=1, le=5000)] = 500,
                   since: Annotated[float | None, Query(description="only samples at or after this time (s)")] = None,
                   until: Annotated[float | None, Query(description="only samples before this time (s)")] = None) -> TelemetryListPublic:
    """Telemetry samples of a session in sequence order, optionally within a time range."""
    get_session_or_404(db, session_id)
    q = select(TelemetrySample).where(TelemetrySample.session_id == session_id)
    if since is not None:
        q = q.where(TelemetrySample.timestamp >= since)
    if until is not None:
        q = q.where(TelemetrySample.timestamp < until)
    count = db.scalar(select(func.count()).select_from(q.subquery())) or 0
    rows = db.scalars(q.order_by(TelemetrySample.seq).offset(skip).limit(limit))
    return TelemetryListPublic(data=list(rows), count=count)  # type: ignore[arg-type]


def defects_query(session_id: str, *, defect_class: str | None = None, source: str | None = None,
                  review_status: str | None = None, condition_state: str | None = None, sort: str = "id") -> Any:
    """SELECT of a session's defects with the list's filters and order (nulls last)."""
    q = select(Defect).where(Defect.session_id == session_id)
    if defect_class:
        q = q.where(Defect.defect_class == defect_class)
    if source:
        q = q.where(Defect.source == source)
    if review_status:
        q = q.where(Defect.review_status == review_status)
    if condition_state:
        q = q.where(Defect.condition_state == condition_state)
    column = getattr(Defect, sort.lstrip("-"))
    order = column.desc() if sort.startswith("-") else column.asc()
    return q.order_by(column.is_(None), order, Defect.id)


@router.get("/{session_id}/defects", response_model=DefectsPublic)
def read_defects(db: SessionDep, session_id: str, defect_class: str | None = None,
                 source: Annotated[str | None, Query(pattern="^(mosaic|frame)$")] = None,
                 review_status: ReviewStatus | None = None, condition_state: ConditionState | None = None,
                 sort: Annotated[str, Query(pattern=DEFECT_SORT, description="a column, '-' before it for descending")] = "id",
                 skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0, limit: Annotated[int, Query(ge=1, le=5000)] = 1000) -> DefectsPublic:
    """Defects found in a session, filtered by class, source (mosaic or frame), review status
    or condition state, sorted by a column."""
    get_session_or_404(db, session_id)
    q = defects_query(session_id, defect_class=defect_class, source=source, review_status=review_status,
                      condition_state=condition_state, sort=sort)
    count = db.scalar(select(func.count()).select_from(q.order_by(None).subquery())) or 0
    rows = db.scalars(q.offset(skip).limit(limit))
    return DefectsPublic(data=list(rows), count=count)  # type: ignore[arg-type]


def _defect_or_404(db: SessionDep, session_id: str, defect_id: int) -> Defect:
    defect = db.get(Defect, defect_id)
    if defect is None or defect.session_id != session_id:
        raise NotFound(f"defect {defect_id} of session {session_id} not found")
    return defect


@router.get("/{session_id}/defects/{defect_id}", response_model=DefectPublic)
def read_defect(db: SessionDep, session_id: str, defect_id: Annotated[int, Path(ge=1, le=MAX_INT)]) -> Defect:
    """One defect."""
    return _defect_or_404(db, session_id, defect_id)


@router.patch("/{session_id}/defects/{defect_id}", response_model=DefectPublic)
def review_defect(db: SessionDep, session_id: str, defect_id: Annotated[int, Path(ge=1, le=MAX_INT)], body: DefectReview,
                  user: OperatorUser) -> Defect:
    """Record an inspector's review of a defect: confirm or reject, condition state CS1–CS4,
    comment (operator role). Who and when is kept for the report."""
    defect = _defect_or_404(db, session_id, defect_id)
    if body.review_status is not None:
        defect.review_status = body.review_status
    if body.condition_state is not None:
        defect.condition_state = body.condition_state
    elif body.clear_condition_state:
        defect.condition_state = None
    if body.comment is not None:
        defect.comment = body.comment
    defect.reviewed_by, defect.reviewed_at = user.name, utcnow()
    db.commit()
    return defect


@router.get("/{session_id}/defects/{defect_id}/thumbnail.jpg", response_class=Response)
async def read_defect_thumbnail(db: SessionDep, state: StateDep, session_id: str, defect_id: Annotated[int, Path(ge=1, le=MAX_INT)],
                                size: Annotated[int, Query(ge=32, le=1024)] = 256) -> Response:
    """The defect's neighbourhood (from its frame or the mosaic) with its box drawn, as JPEG."""
    defect = _defect_or_404(db, session_id, defect_id)
    image = await run_in_threadpool(defect_image, db, state.files, defect, size)
    return Response(encode_jpeg(image), media_type="image/jpeg", headers={"Cache-Control": "private, max-age=60"})


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
