"""A job's state transitions, each one conditional UPDATE checked in the database, so that a
job runs to completion at most once however many workers are handed it (a queue that
redelivers after a worker was lost, a station that hands it out again).

An attempt *claims* a queued job, or a running one whose heartbeat is older than the lease
(its worker is gone); the claim numbers the attempt. The attempt then beats while it runs
and finishes the job only while it still holds it: an attempt that was cancelled or taken
over finds its UPDATE matching no row, and its result is dropped.
"""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime, timedelta, timezone
from typing import Any

from sqlalchemy import and_, or_, update
from sqlalchemy.orm import Session, sessionmaker

from server.storage.models import Job, JobState, utcnow

LEASE_S = 60.0  # a running job silent this long has lost its worker
ENDED = (JobState.done, JobState.failed, JobState.cancelled)


def claim(
    factory: sessionmaker[Session], job_id: int, worker: str, lease_s: float = LEASE_S
) -> int | None:
    """Take the job for a new attempt: its number, or None when the job is ended or another
    live attempt holds it."""
    now = utcnow()
    stale = now - timedelta(seconds=lease_s)
    with factory() as db:
        attempt = db.execute(
            update(Job)
            .where(
                Job.id == job_id,
                or_(
                    Job.state == JobState.queued,
                    and_(
                        Job.state == JobState.running,
                        or_(Job.heartbeat_at.is_(None), Job.heartbeat_at < stale),
                    ),
                ),
            )
            .values(
                state=JobState.running,
                attempt=Job.attempt + 1,
                worker=worker,
                heartbeat_at=now,
                started_at=now,
                progress=0.0,
                message="",
                error=None,
            )
            .returning(Job.attempt)
        ).scalar()
        db.commit()
    return attempt


def holder_alive_for(
    factory: sessionmaker[Session], job_id: int, lease_s: float = LEASE_S
) -> float | None:
    """Seconds until a running job's lease runs out (None: the job is not running)."""
    with factory() as db:
        job = db.get(Job, job_id)
        if job is None or job.state != JobState.running:
            return None
        if job.heartbeat_at is None:
            return 0.0
        beat_at = job.heartbeat_at
        if beat_at.tzinfo is None:  # SQLite keeps UTC without its zone
            beat_at = beat_at.replace(tzinfo=timezone.utc)
        return max(0.0, lease_s - (utcnow() - beat_at).total_seconds())


def beat(
    factory: sessionmaker[Session],
    job_id: int,
    attempt: int,
    *,
    progress: float | None = None,
    message: str | None = None,
) -> bool:
    """Renew the lease (and record progress); False when this attempt no longer holds the
    job (cancelled, or taken over after its heartbeat stopped)."""
    values: dict[str, Any] = {"heartbeat_at": utcnow()}
    if progress is not None:
        values["progress"] = float(min(max(progress, 0.0), 1.0))
    if message is not None:
        values["message"] = message
    with factory() as db:
        held = db.execute(_held(job_id, attempt).values(**values)).rowcount == 1
        db.commit()
    return held


def finish(
    factory: sessionmaker[Session],
    job_id: int,
    attempt: int,
    state: JobState,
    *,
    error: str | None = None,
    result: dict[str, Any] | None = None,
    then: Callable[[Session], None] | None = None,
    publish: Callable[[], None] | None = None,
) -> bool:
    """End the job as ``state`` with its result or error, if this attempt still holds it.

    In the same transaction: ``then(db)`` first (the job's database writes; it may still
    fill in ``result``), then the conditional update, then ``publish()`` (the job's files)
    only when the job was this attempt's. A concurrent cancel either ends the job first
    (the writes are rolled back) or waits and finds it ended. When ``then`` or ``publish``
    raises, nothing is recorded and the error propagates."""
    with factory() as db:
        try:
            if then is not None:
                then(db)
            values: dict[str, Any] = {"state": state, "finished_at": utcnow(), "error": error}
            if result is not None:
                values.update(result=result, progress=1.0)
            ended = db.execute(_held(job_id, attempt).values(**values)).rowcount == 1
            if not ended:
                db.rollback()
                return False
            if publish is not None:
                publish()
        except BaseException:
            db.rollback()
            raise
        db.commit()
    return True


def cancel(factory: sessionmaker[Session], job_id: int, by: str) -> bool:
    """Cancel a queued or running job (False: it had ended already). A running attempt stops
    at its next heartbeat or progress report."""
    with factory() as db:
        done = (
            db.execute(
                update(Job)
                .where(Job.id == job_id, Job.state.in_([JobState.queued, JobState.running]))
                .values(state=JobState.cancelled, finished_at=utcnow(), error=f"cancelled by {by}")
            ).rowcount
            == 1
        )
        db.commit()
    return done


def fail_unless_ended(factory: sessionmaker[Session], job_id: int, error: str) -> None:
    """Mark a job failed whatever attempt holds it (its worker died under the station)."""
    with factory() as db:
        db.execute(
            update(Job)
            .where(Job.id == job_id, Job.state.not_in(ENDED))
            .values(state=JobState.failed, finished_at=utcnow(), error=error)
        )
        db.commit()


def stale_before(lease_s: float = LEASE_S) -> datetime:
    """Heartbeats older than this are of lost workers."""
    return utcnow() - timedelta(seconds=lease_s)


def _held(job_id: int, attempt: int) -> Any:
    return update(Job).where(
        Job.id == job_id, Job.attempt == attempt, Job.state == JobState.running
    )
