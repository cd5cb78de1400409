"""Processing jobs: list a session's, start one, read one, cancel one."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Path, status
from sqlalchemy import select

from server.api.deps import OperatorUser, SessionDep, StateDep, get_current_user
from server.api.queries import get_session_or_404
from server.api.schemas import JobCreate, JobPublic
from server.errors import Conflict, NotFound
from server.storage.models import Job

router = APIRouter(prefix="/api", tags=["jobs"], dependencies=[Depends(get_current_user)])


@router.get("/sessions/{session_id}/jobs", response_model=list[JobPublic])
def read_session_jobs(db: SessionDep, session_id: str) -> list[Job]:
    """Jobs of a session, oldest first."""
    get_session_or_404(db, session_id)
    return list(db.scalars(select(Job).where(Job.session_id == session_id).order_by(Job.id)))


@router.post(
    "/sessions/{session_id}/jobs", response_model=JobPublic, status_code=status.HTTP_202_ACCEPTED
)
def create_job(
    db: SessionDep, state: StateDep, session_id: str, body: JobCreate, _: OperatorUser
) -> Job:
    """Queue a processing job (stitch, map, detect, or export: the session as MCAP) for a session (operator role)."""
    get_session_or_404(db, session_id)
    after: list[int] = []
    if body.kind == "detect":
        last_stitch = db.scalar(
            select(Job.id)
            .where(Job.session_id == session_id, Job.kind == "stitch")
            .order_by(Job.id.desc())
        )
        if last_stitch is not None:
            after = [last_stitch]
    params = {"method": body.method} if body.method is not None else None
    job_id = state.jobs.enqueue(session_id, body.kind, after=after, params=params)
    job = db.get(Job, job_id)
    assert job is not None
    return job


@router.get("/jobs/{job_id}", response_model=JobPublic)
def read_job(db: SessionDep, job_id: Annotated[int, Path(ge=1, le=2**63 - 1)]) -> Job:
    """One job with its state, progress and result."""
    job = db.get(Job, job_id)
    if job is None:
        raise NotFound(f"job {job_id} not found")
    return job


@router.post("/jobs/{job_id}/cancel", response_model=JobPublic)
def cancel_job(
    db: SessionDep,
    state: StateDep,
    user: OperatorUser,
    job_id: Annotated[int, Path(ge=1, le=2**63 - 1)],
) -> Job:
    """Cancel a queued or running job (operator role): a running one stops at its next
    progress report, wherever its worker is; jobs that need its result fail. 409 when the
    job has ended."""
    if db.get(Job, job_id) is None:
        raise NotFound(f"job {job_id} not found")
    if not state.jobs.cancel(job_id, user.name):
        raise Conflict(f"job {job_id} has ended already")
    db.expire_all()
    job = db.get(Job, job_id)
    assert job is not None
    return job
