"""Job leases on both databases: one attempt holds a job; a silent one is taken over and its
late result dropped; cancelling ends the job for every attempt."""

from __future__ import annotations

import time
import uuid

import pytest
from sqlalchemy.orm import Session, sessionmaker

from server.jobs import leases
from server.storage.db import make_engine, make_sessionmaker, upgrade
from server.storage.models import InspectionSession, Job, JobState


@pytest.fixture
def factory(database_url: str):  # type: ignore[no-untyped-def]
    upgrade(database_url)
    engine = make_engine(database_url)
    yield make_sessionmaker(engine)
    engine.dispose()


def new_job(factory: sessionmaker[Session]) -> int:
    with factory() as db:
        sid = str(uuid.uuid4())
        db.add(InspectionSession(id=sid, structure="leased"))
        db.flush()
        job = Job(session_id=sid, kind="stitch")
        db.add(job)
        db.commit()
        return job.id


def state(factory: sessionmaker[Session], job_id: int) -> Job:
    with factory() as db:
        job = db.get(Job, job_id)
        assert job is not None
        return job


def test_one_attempt_holds_a_job_and_finishes_it_once(factory) -> None:  # type: ignore[no-untyped-def]
    job_id = new_job(factory)
    first = leases.claim(factory, job_id, "a")
    assert first == 1
    assert leases.claim(factory, job_id, "b") is None  # a live attempt holds it
    assert leases.beat(factory, job_id, first, progress=0.5, message="half")
    assert state(factory, job_id).progress == 0.5
    assert leases.finish(factory, job_id, first, JobState.done, result={"n": 1})
    assert not leases.finish(factory, job_id, first, JobState.done, result={"n": 2})
    assert leases.claim(factory, job_id, "b") is None  # ended: nothing to run
    job = state(factory, job_id)
    assert (job.state, job.result, job.worker, job.attempt) == (JobState.done, {"n": 1}, "a", 1)


def test_a_silent_attempt_is_taken_over_and_its_late_result_dropped(factory) -> None:  # type: ignore[no-untyped-def]
    job_id = new_job(factory)
    lease_s = 0.3
    first = leases.claim(factory, job_id, "lost", lease_s)
    assert leases.holder_alive_for(factory, job_id, lease_s) > 0
    time.sleep(lease_s + 0.1)
    assert leases.holder_alive_for(factory, job_id, lease_s) == 0
    second = leases.claim(factory, job_id, "new", lease_s)
    assert second == 2
    assert not leases.beat(factory, job_id, first)  # the first attempt learns it lost the job
    assert not leases.finish(factory, job_id, first, JobState.failed, error="late")
    assert leases.finish(factory, job_id, second, JobState.done, result={"ok": True})
    job = state(factory, job_id)
    assert (job.state, job.error, job.worker) == (JobState.done, None, "new")


def test_cancelling_ends_the_job_for_the_attempt_running_it(factory) -> None:  # type: ignore[no-untyped-def]
    job_id = new_job(factory)
    attempt = leases.claim(factory, job_id, "a")
    assert attempt is not None
    assert leases.cancel(factory, job_id, "inspector")
    assert not leases.cancel(factory, job_id, "inspector")
    assert not leases.beat(factory, job_id, attempt)
    assert not leases.finish(factory, job_id, attempt, JobState.done, result={"n": 1})
    job = state(factory, job_id)
    assert (job.state, job.error, job.result) == (JobState.cancelled, "cancelled by inspector", {})


def test_a_finish_that_lost_the_job_rolls_back_its_writes_and_publishes_nothing(factory) -> None:  # type: ignore[no-untyped-def]
    published: list[int] = []
    result: dict[str, int] = {}

    def finish_writing(job_id: int, attempt: int) -> bool:
        def write(db: Session) -> None:  # the job's own rows, in the finishing transaction
            db.add(InspectionSession(id=f"written-{job_id}", structure="by the job"))
            result["rows"] = 1

        return leases.finish(
            factory,
            job_id,
            attempt,
            JobState.done,
            result=result,
            then=write,
            publish=lambda: published.append(job_id),
        )

    job_id = new_job(factory)
    attempt = leases.claim(factory, job_id, "a")
    assert attempt is not None
    assert leases.cancel(factory, job_id, "inspector")
    assert not finish_writing(job_id, attempt)
    assert published == []
    with factory() as db:
        assert db.get(InspectionSession, f"written-{job_id}") is None
    assert state(factory, job_id).state == JobState.cancelled

    job_id = new_job(factory)
    attempt = leases.claim(factory, job_id, "a")
    assert attempt is not None
    assert finish_writing(job_id, attempt)
    assert published == [job_id]
    with factory() as db:
        assert db.get(InspectionSession, f"written-{job_id}") is not None
    assert state(factory, job_id).result == {"rows": 1}  # filled in by the writes
