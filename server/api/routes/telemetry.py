"""A session's telemetry samples."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query
from sqlalchemy import select

from server.api.deps import SessionDep, get_current_user
from server.api.queries import MAX_INT, count_query, get_session_or_404
from server.api.schemas import TelemetryListPublic
from server.storage.models import TelemetrySample

router = APIRouter(
    prefix="/api/sessions", tags=["telemetry"], dependencies=[Depends(get_current_user)]
)


@router.get("/{session_id}/telemetry", response_model=TelemetryListPublic)
def read_telemetry(
    db: SessionDep,
    session_id: str,
    skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0,
    limit: Annotated[int, Query(ge=1, le=5000)] = 500,
    since: Annotated[
        float | None, Query(description="only samples at or after this time (s)")
    ] = None,
    until: Annotated[float | None, Query(description="only samples before this time (s)")] = None,
) -> TelemetryListPublic:
    """Telemetry samples of a session in sequence order, optionally within a time range."""
    get_session_or_404(db, session_id)
    q = select(TelemetrySample).where(TelemetrySample.session_id == session_id)
    if since is not None:
        q = q.where(TelemetrySample.timestamp >= since)
    if until is not None:
        q = q.where(TelemetrySample.timestamp < until)
    rows = db.scalars(q.order_by(TelemetrySample.seq).offset(skip).limit(limit))
    return TelemetryListPublic(data=list(rows), count=count_query(db, q))  # type: ignore[arg-type]
