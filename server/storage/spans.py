"""How long a session lasted: the span of its data's timestamps (the robot's clock, which a
simulated or replayed inspection sets), else of the station's start and end times."""

from __future__ import annotations

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.storage.models import Cloud, Frame, InspectionSession, TelemetrySample, utcnow


def data_span(db: Session, session_id: str) -> tuple[float, float] | None:
    """First and last timestamp (s, robot clock) of a session's frames, clouds and
    telemetry; None when it stored none."""
    lo: list[float] = []
    hi: list[float] = []
    for model in (TelemetrySample, Frame, Cloud):
        first, last = db.execute(
            select(func.min(model.timestamp), func.max(model.timestamp)).where(
                model.session_id == session_id
            )
        ).one()
        if first is not None:
            lo.append(float(first))
            hi.append(float(last))
    return (min(lo), max(hi)) if lo else None


def duration_s(db: Session, s: InspectionSession) -> float:
    """Seconds the inspection lasted: its data's span, or the station's clock while the
    session stored nothing yet (a live session: up to now)."""
    span = data_span(db, s.id)
    if span is not None:
        return max(0.0, span[1] - span[0])
    start, end = (
        t.replace(tzinfo=None) if t.tzinfo else t for t in (s.started_at, s.ended_at or utcnow())
    )
    return max(0.0, (end - start).total_seconds())
