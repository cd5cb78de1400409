"""Inspection sessions: list, read, correct."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query
from sqlalchemy import func, or_, select

from server.api.deps import OperatorUser, SessionDep, get_current_user
from server.api.queries import MAX_INT, count_query, get_session_or_404, session_public
from server.api.schemas import SessionPublic, SessionsPublic, SessionUpdate, Text
from server.storage.models import InspectionSession, Robot, SessionStatus

router = APIRouter(
    prefix="/api/sessions", tags=["sessions"], dependencies=[Depends(get_current_user)]
)


@router.get("", response_model=SessionsPublic)
def read_sessions(
    db: SessionDep,
    skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0,
    limit: Annotated[int, Query(ge=1, le=500)] = 100,
    q: Annotated[
        Text,
        Query(
            max_length=200,
            description="words that must each appear in the structure, location, operator, "
            "notes, robot name or id (case-insensitive)",
        ),
    ] = "",
    status: Annotated[SessionStatus | None, Query()] = None,
) -> SessionsPublic:
    """List inspection sessions, newest first; ``q`` and ``status`` narrow the list
    (``count`` is of the narrowed list)."""
    query = select(InspectionSession).outerjoin(Robot, InspectionSession.robot_id == Robot.id)
    for word in q.split():
        pattern = (
            "%" + word.lower().replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_") + "%"
        )
        fields = (
            InspectionSession.structure,
            InspectionSession.location,
            InspectionSession.operator,
            InspectionSession.notes,
            InspectionSession.id,
            Robot.name,
        )
        query = query.where(or_(*(func.lower(f).like(pattern, escape="\\") for f in fields)))
    if status is not None:
        query = query.where(InspectionSession.status == status)
    count = count_query(db, query)
    rows = db.scalars(query.order_by(InspectionSession.started_at.desc()).offset(skip).limit(limit))
    return SessionsPublic(data=[session_public(db, s) for s in rows], count=count)


@router.get("/{session_id}", response_model=SessionPublic)
def read_session(db: SessionDep, session_id: str) -> SessionPublic:
    """One session with counts of what it stored and its jobs."""
    return session_public(db, get_session_or_404(db, session_id))


@router.patch("/{session_id}", response_model=SessionPublic)
def update_session(
    db: SessionDep, session_id: str, body: SessionUpdate, _: OperatorUser
) -> SessionPublic:
    """Correct a session's structure, location, operator or notes (operator role)."""
    s = get_session_or_404(db, session_id)
    for name, value in body.model_dump(exclude_none=True).items():
        setattr(s, name, value)
    db.commit()
    return session_public(db, s)
