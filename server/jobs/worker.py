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
from typing import Any, Literal

from sqlalchemy.orm import Session, sessionmaker

from server.jobs import leases, outputs
from server.jobs.context import Fanout, Heartbeat, JobContext, JobLost
from server.jobs.detect import run_detect
from server.jobs.export import run_export
from server.jobs.leases import LEASE_S
from server.jobs.map import run_map
from server.jobs.stitch import run_stitch
from server.storage.db import make_engine, make_sessionmaker
from server.storage.files import SessionFiles
from server.storage.models import Job, JobState

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
def factory_for(database_url: str) -> sessionmaker[Session]:
    return make_sessionmaker(make_engine(database_url))


Outcome = Literal["done", "failed", "lost", "held", "ended"]


def run_job(
    job_id: int,
    database_url: str,
    data_dir: str,
    *,
    worker: str = "station",
    lease_s: float = LEASE_S,
    threads: int = 2,
    fanout: Fanout | None = None,
) -> Outcome:
    """Run one job to completion under a lease (:mod:`server.jobs.leases`), recording
    success or the reason it failed. The outcome: ``done``/``failed``; ``lost`` when the
    attempt was cancelled or taken over while it ran (its result dropped); ``held`` when a
    live attempt elsewhere holds the job; ``ended`` when there was nothing to run."""
    factory = factory_for(database_url)
    attempt = leases.claim(factory, job_id, worker, lease_s)
    if attempt is None:
        return "held" if leases.holder_alive_for(factory, job_id, lease_s) is not None else "ended"
    with factory() as db:
        job = db.get(Job, job_id)
        assert job is not None
        kind, session_id, params = job.kind, job.session_id, dict(job.params or {})
    ctx = JobContext(
        job_id,
        session_id,
        factory,
        SessionFiles(Path(data_dir)),
        params,
        attempt=attempt,
        threads=threads,
        fanout=fanout,
    )
    results = ctx.results_dir()
    staging = outputs.staging_dir(results, job_id, attempt)
    outputs.discard_earlier(results, job_id, attempt)

    try:
        with Heartbeat(ctx, lease_s / 4):
            try:
                result = JOB_KINDS[kind](ctx)
            except JobLost:
                log.info("job %d (%s) attempt %d: cancelled or taken over", job_id, kind, attempt)
                return "lost"
            except Exception as exc:  # a job's failure is recorded, never raised into the runner
                log.error("job %d (%s) failed:\n%s", job_id, kind, traceback.format_exc())
                return _failed(factory, job_id, attempt, exc)
        return _finished(ctx, kind, result, lambda: outputs.publish(staging, results))
    finally:
        outputs.discard(staging)  # what was not published: dropped


def _finished(
    ctx: JobContext, kind: str, result: dict[str, Any], publish: Callable[[], None]
) -> Outcome:
    """Record the job done: its database writes and files become the session's with the
    job's end, if the attempt still holds it; failed when they cannot be stored."""
    try:
        held = leases.finish(
            ctx.factory,
            ctx.job_id,
            ctx.attempt,
            JobState.done,
            result=result,
            then=ctx.store,
            publish=publish,
        )
    except Exception as exc:  # its results could not be stored (disk, database)
        log.error("job %d (%s) not stored:\n%s", ctx.job_id, kind, traceback.format_exc())
        return _failed(ctx.factory, ctx.job_id, ctx.attempt, exc)
    return "done" if held else "lost"


def _failed(factory: sessionmaker[Session], job_id: int, attempt: int, exc: Exception) -> Outcome:
    held = leases.finish(
        factory, job_id, attempt, JobState.failed, error=f"{type(exc).__name__}: {exc}"
    )
    return "failed" if held else "lost"
