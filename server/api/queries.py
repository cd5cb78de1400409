"""Data access for the routes: the rows a request names, or :class:`NotFound`; counts; filters."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Path
from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session

from server.api.schemas import JobPublic, ResultsCover, SessionPublic
from server.errors import NotFound
from server.jobs.inputs import is_current, latest_inputs, stored_inputs
from server.reports.fields import IMPORTED_FROM
from server.storage.files import SessionFiles
from server.storage.models import Cloud, Defect, Frame, InspectionSession, Job, Structure
from server.storage.spans import duration_s

MAX_INT = 2**63 - 1  # SQLite's largest integer: a bigger id cannot exist
Seq = Annotated[int, Path(ge=0, le=MAX_INT)]
DefectId = Annotated[int, Path(ge=1, le=MAX_INT)]
DEFECT_SORT_KEYS = (
    "id",
    "number",
    "defect_class",
    "source",
    "length_mm",
    "max_width_mm",
    "area_mm2",
    "area_px",
    "length_px",
    "world_x_m",
    "world_y_m",
    "review_status",
    "condition_state",
    "confidence",
)


def count_rows(db: Session, model: Any, session_id: str) -> int:
    """Rows of ``model`` (a table with ``session_id``) in one session."""
    return (
        db.scalar(select(func.count()).select_from(model).where(model.session_id == session_id))
        or 0
    )


def count_query(db: Session, q: Select[Any]) -> int:
    """Rows a SELECT would return."""
    return db.scalar(select(func.count()).select_from(q.order_by(None).subquery())) or 0


def get_session_or_404(db: Session, session_id: str) -> InspectionSession:
    """The session, or NotFound."""
    s = db.get(InspectionSession, session_id)
    if s is None:
        raise NotFound(f"session {session_id} not found")
    return s


def get_structure_or_404(db: Session, structure_id: int) -> Structure:
    """The structure, or NotFound."""
    s = db.get(Structure, structure_id)
    if s is None:
        raise NotFound(f"structure {structure_id} not found")
    return s


def session_public(db: Session, s: InspectionSession, *, with_jobs: bool = True) -> SessionPublic:
    """A session with counts of what it stored (and its jobs)."""
    out = SessionPublic.model_validate(s)
    now = stored_inputs(db, s.id)
    out.frames, out.clouds, out.telemetry = now["frames"], now["clouds"], now["telemetry"]
    inputs = latest_inputs(db, s.id)
    if inputs is not None:
        out.results_cover = ResultsCover(
            frames=inputs.get("frames", 0),
            clouds=inputs.get("clouds", 0),
            telemetry=inputs.get("telemetry", 0),
            current=is_current(inputs, now),
        )
    defects = select(func.count()).select_from(Defect).where(Defect.session_id == s.id)
    out.defects = db.scalar(defects.where(Defect.source == "mosaic")) or 0
    out.frame_defects = db.scalar(defects.where(Defect.source == "frame")) or 0
    out.robot_name = s.robot.name if s.robot else None
    out.imported = s.robot_id is None and IMPORTED_FROM in (s.notes or "")
    out.duration_s = duration_s(db, s)
    if with_jobs:
        jobs = db.scalars(select(Job).where(Job.session_id == s.id).order_by(Job.id))
        out.jobs = [JobPublic.model_validate(j) for j in jobs]
    return out


def get_frame_or_404(db: Session, session_id: str, seq: int) -> Frame:
    """Frame ``seq`` of a session, or NotFound."""
    frame = db.scalar(select(Frame).where(Frame.session_id == session_id, Frame.seq == seq))
    if frame is None:
        raise NotFound(f"frame {seq} of session {session_id} not found")
    return frame


def get_cloud_or_404(db: Session, session_id: str, seq: int) -> Cloud:
    """Cloud ``seq`` of a session, or NotFound."""
    cloud = db.scalar(select(Cloud).where(Cloud.session_id == session_id, Cloud.seq == seq))
    if cloud is None:
        raise NotFound(f"cloud {seq} of session {session_id} not found")
    return cloud


def get_defect_or_404(db: Session, session_id: str, defect_id: int) -> Defect:
    """A defect of a session, or NotFound."""
    defect = db.get(Defect, defect_id)
    if defect is None or defect.session_id != session_id:
        raise NotFound(f"defect {defect_id} of session {session_id} not found")
    return defect


def read_payload(files: SessionFiles, row: Frame | Cloud, what: str) -> bytes:
    """A frame's or cloud's stored bytes; NotFound when they cannot be read."""
    try:
        return files.payload(row)
    except (OSError, ValueError) as exc:
        raise NotFound(f"the data of {what} cannot be read: {exc}") from None


def defects_query(
    session_id: str,
    *,
    defect_class: str | None = None,
    source: str | None = None,
    review_status: str | None = None,
    condition_state: str | None = None,
    below_confidence: float | None = None,
    sort: str = "id",
) -> Select[Any]:
    """SELECT of a session's defects with the list's filters (``below_confidence``: only
    defects the detector is less sure of than that) and order (nulls last)."""
    q = select(Defect).where(Defect.session_id == session_id)
    if defect_class:
        q = q.where(Defect.defect_class == defect_class)
    if source:
        q = q.where(Defect.source == source)
    if review_status:
        q = q.where(Defect.review_status == review_status)
    if condition_state:
        q = q.where(Defect.condition_state == condition_state)
    if below_confidence is not None:
        q = q.where(Defect.confidence.is_not(None), Defect.confidence < below_confidence)
    column = getattr(Defect, sort.lstrip("-"))
    order = column.desc() if sort.startswith("-") else column.asc()
    return q.order_by(column.is_(None), order, Defect.id)
