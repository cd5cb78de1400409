"""What a job reads of its session: the frames, clouds and telemetry stored when it was
queued. A job's inputs are fixed then (the largest row id of each kind), so every stage of
one pipeline reads the same data, however much arrives while it runs; data stored later
(a robot's resends after its SESSION_END) makes the results stale, and :func:`is_current`
says so."""

from __future__ import annotations

from typing import Any

from sqlalchemy import ColumnElement, Select, func, select, true
from sqlalchemy.orm import Session

from server.storage.models import Cloud, Frame, Job, TelemetrySample

KINDS: dict[str, Any] = {"frames": Frame, "clouds": Cloud, "telemetry": TelemetrySample}


def stored_inputs(db: Session, session_id: str) -> dict[str, int]:
    """What a session holds now: for each kind its count (``frames``) and largest row id
    (``frames_upto``)."""
    out: dict[str, int] = {}
    for name, model in KINDS.items():
        count, upto = db.execute(
            select(func.count(), func.max(model.id)).where(model.session_id == session_id)
        ).one()
        out[name] = int(count or 0)
        out[f"{name}_upto"] = int(upto or 0)
    return out


def within(model: Any, inputs: dict[str, int] | None) -> ColumnElement[bool]:
    """The condition that keeps a row of ``model`` (Frame, Cloud, TelemetrySample) among a
    job's fixed inputs (all rows for a job queued without them)."""
    name = next(k for k, m in KINDS.items() if m is model)
    if not inputs or f"{name}_upto" not in inputs:
        return true()
    return model.id <= inputs[f"{name}_upto"]


def rows_of(model: Any, session_id: str, inputs: dict[str, int] | None) -> Select[Any]:
    """SELECT of a session's rows of ``model`` within a job's inputs, in seq order."""
    return (
        select(model)
        .where(model.session_id == session_id, within(model, inputs))
        .order_by(model.seq)
    )


def latest_processing(db: Session, session_id: str) -> Job | None:
    """The session's newest processing: its newest stitch job, if any."""
    return db.scalars(
        select(Job)
        .where(Job.session_id == session_id, Job.kind == "stitch")
        .order_by(Job.id.desc())
        .limit(1)
    ).first()


def latest_inputs(db: Session, session_id: str) -> dict[str, int] | None:
    """The inputs of the session's newest processing; None when it was never processed, or
    processed before a job recorded its inputs."""
    job = latest_processing(db, session_id)
    return None if job is None else (job.params or {}).get("inputs")


def is_current(inputs: dict[str, int] | None, now: dict[str, int]) -> bool:
    """Whether processing with ``inputs`` covers everything in ``now``."""
    return inputs is not None and all(inputs.get(k, -1) >= v for k, v in now.items())
