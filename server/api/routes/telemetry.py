"""A session's telemetry samples."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query
from pydantic import StringConstraints
from sqlalchemy import select

from server.api.deps import SessionDep, get_current_user
from server.api.queries import MAX_INT, count_query, get_session_or_404
from server.api.schemas import TelemetryListPublic
from server.reports.timeline import telemetry_fields, telemetry_series
from server.storage.models import TelemetrySample

MAX_SERIES = 12  # fields plotted at once

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


@router.get("/{session_id}/telemetry/series")
def read_telemetry_series(
    db: SessionDep,
    session_id: str,
    field: Annotated[
        list[Annotated[str, StringConstraints(min_length=1, max_length=200)]],
        Query(
            min_length=1,
            max_length=MAX_SERIES,
            description="flattened field names, as GET /api/sessions/{id}/timeline lists them "
            '(e.g. "battery_v.main", "wheel_speed_mps[0]")',
        ),
    ],
    max_points: Annotated[int, Query(ge=2, le=20000)] = 4000,
) -> dict[str, Any]:
    """Numeric telemetry fields over the whole session, for plotting: ``timestamps`` (robot
    clock, s), one list of values per field (``null`` where a sample lacks it), the
    ``units`` the protocol's key suffixes name, and the ``stride`` (every k-th sample is
    kept when there are more than ``max_points``)."""
    get_session_or_404(db, session_id)
    return telemetry_series(db, session_id, list(dict.fromkeys(field)), max_points)


@router.get("/{session_id}/telemetry/fields")
def read_telemetry_fields(db: SessionDep, session_id: str) -> dict[str, Any]:
    """The numeric fields the session's telemetry holds (flattened names, as the series
    take them) with the units the protocol's key suffixes name."""
    get_session_or_404(db, session_id)
    return telemetry_fields(db, session_id)
