"""What a worker process runs: one job, by id, to completion or a recorded failure.

The jobs and the order they run in after a session ends (:data:`PIPELINE`) are defined here;
each job's body is a module of its own. This is the edge where files and rows become arrays
and back; the algorithms themselves live in ``processing``.
"""

from __future__ import annotations

import logging
import traceback
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from server.jobs.context import JobContext
from server.jobs.detect import run_detect
from server.jobs.export import run_export
from server.jobs.map import run_map
from server.jobs.stitch import run_stitch
from server.storage.db import make_engine, make_sessionmaker
from server.storage.files import SessionFiles
from server.storage.models import Job, JobState, utcnow

log = logging.getLogger(__name__)

# (kind, needs: fails without them, uses: waits for them and uses their results if any)
PIPELINE: list[tuple[str, list[str], list[str]]] = [
    ("stitch", [], []),
    ("map", [], ["stitch"]),
    ("detect", ["stitch"], []),
    ("export", [], ["stitch", "map", "detect"]),
]
JOB_KINDS: dict[str, Callable[[JobContext], dict[str, Any]]] = {
    "stitch": run_stitch,
    "map": run_map,
    "detect": run_detect,
    "export": run_export,
}


@lru_cache(maxsize=4)
def _factory(database_url: str) -> sessionmaker[Session]:
    return make_sessionmaker(make_engine(database_url))


def run_job(job_id: int, database_url: str, data_dir: str) -> None:
    """Run one job to completion, recording success or the reason it failed."""
    factory = _factory(database_url)
    with factory() as db:
        job = db.get(Job, job_id)
        if job is None:
            return
        job.state, job.started_at, job.progress, job.error = JobState.running, utcnow(), 0.0, None
        db.commit()
        kind, session_id, params = job.kind, job.session_id, dict(job.params or {})
    ctx = JobContext(job_id, session_id, factory, SessionFiles(Path(data_dir)), params)
    try:
        result = JOB_KINDS[kind](ctx)
    except Exception as exc:  # a job's failure is recorded, never raised into the runner
        log.error("job %d (%s) failed:\n%s", job_id, kind, traceback.format_exc())
        _finish(factory, job_id, JobState.failed, error=f"{type(exc).__name__}: {exc}")
        return
    _finish(factory, job_id, JobState.done, result=result)


def _finish(
    factory: sessionmaker[Session],
    job_id: int,
    state: JobState,
    *,
    error: str | None = None,
    result: dict[str, Any] | None = None,
) -> None:
    with factory() as db:
        job = db.get(Job, job_id)
        if job is None:
            return
        job.state, job.finished_at, job.error = state, utcnow(), error
        if result is not None:
            job.result, job.progress = result, 1.0
        db.commit()
