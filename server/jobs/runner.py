"""The station's job dispatcher: a thread that hands each queued job, once the jobs it
depends on have ended, to a pool of worker processes of its own (the default) or to a job
queue (Celery workers anywhere, :mod:`server.jobs.queue`)."""

from __future__ import annotations

import logging
import multiprocessing
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from functools import partial
from typing import Any

from sqlalchemy import or_, select, update
from sqlalchemy.orm import Session, sessionmaker

from server.jobs import leases
from server.jobs.inputs import is_current, latest_inputs, latest_processing, stored_inputs
from server.jobs.worker import JOB_KINDS, PIPELINE, run_job
from server.process.orphans import init_worker
from server.process.pools import stop_pool
from server.storage.models import InspectionSession, Job, JobState, SessionStatus, utcnow

Send = Callable[[int], None]  # hands a job id to a job queue
MAX_ATTEMPTS = 3  # attempts a job gets when the station stops under it

log = logging.getLogger(__name__)


class JobRunner:
    """Runs queued jobs in worker processes once the jobs they depend on are done.

    A job's failure (an exception, or its worker process dying) marks that job failed with
    the reason and leaves the runner and the server running.

    With ``send`` (a job queue), jobs are handed to it instead, each once, and again when
    its worker's heartbeat stops for a lease; the workers claim them (:mod:`leases`).
    """

    def __init__(
        self,
        factory: sessionmaker[Session],
        database_url: str,
        data_dir: str,
        workers: int,
        defaults: dict[str, dict[str, Any]] | None = None,
        *,
        send: Send | None = None,
        lease_s: float = leases.LEASE_S,
        settle_s: float = 2.0,
    ) -> None:
        """``defaults``: parameters per job kind, under those a caller gives; ``settle_s``:
        how long a session that got data after its end stays quiet before it is processed
        again."""
        self.factory = factory
        self.send, self.lease_s = send, lease_s
        self.defaults = defaults or {}
        self.database_url = database_url
        self.data_dir = data_dir
        self.workers = workers
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._running: dict[int, Future[None]] = {}
        self._pool: ProcessPoolExecutor | None = None
        self._thread: threading.Thread | None = None
        self.settle_s = settle_s
        self._stale: dict[str, float] = {}  # session -> when data was last stored after its end
        self._stale_lock = threading.Lock()

    def start(self) -> None:
        """Queue again the jobs a crash of the station interrupted (its own workers died with
        it), up to :data:`MAX_ATTEMPTS` attempts each, then fail them (a job that brings the
        station down every time); a job queue's workers carry on, and queued jobs are handed
        to the queue again, in case the crash came between marking and sending. Then start
        dispatching."""
        if self.send is not None:
            with self.factory() as db:
                db.execute(
                    update(Job).where(Job.state == JobState.queued).values(dispatched_at=None)
                )
                db.commit()
        else:
            with self.factory() as db:
                for job in db.scalars(select(Job).where(Job.state == JobState.running)):
                    if job.attempt < MAX_ATTEMPTS:  # run again: what waits on it waits on
                        job.state, job.worker, job.heartbeat_at = JobState.queued, None, None
                        job.message = "interrupted: the ground station stopped; queued again"
                        continue
                    job.state = JobState.failed
                    job.error = (
                        f"interrupted {job.attempt} times: the ground station stopped while "
                        "the job ran"
                    )
                    job.finished_at = utcnow()
                db.commit()
            self._pool = self._new_pool()
        self._thread = threading.Thread(target=self._loop, name="job-dispatcher", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop dispatching and shut the workers down."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
        if self._pool is not None:
            stop_pool(self._pool)

    def enqueue(
        self,
        session_id: str,
        kind: str,
        *,
        after: list[int] | None = None,
        uses: list[int] | None = None,
        params: dict[str, Any] | None = None,
    ) -> int:
        """Queue one job; it runs when every job in ``after`` is done (and fails if one of them
        failed) and every job in ``uses`` has finished, whichever way (it uses their results
        when there are some)."""
        if kind not in JOB_KINDS:
            raise ValueError(f"kind must be one of {sorted(JOB_KINDS)}, got {kind!r}")
        with self.factory() as db:
            job = Job(
                session_id=session_id,
                kind=kind,
                params={
                    **self.defaults.get(kind, {}),
                    "inputs": stored_inputs(db, session_id),
                    **(params or {}),
                    "after": after or [],
                    "uses": uses or [],
                },
            )
            db.add(job)
            db.commit()
            job_id = job.id
        self._wake.set()
        return job_id

    def cancel(self, job_id: int, by: str) -> bool:
        """Cancel a queued or running job (False: it had ended); jobs waiting on it fail."""
        done = leases.cancel(self.factory, job_id, by)
        self._wake.set()
        return done

    def enqueue_pipeline(self, session_id: str) -> list[int]:
        """Queue every processing stage of a session in dependency order, every stage on
        the data stored now (:mod:`server.jobs.inputs`)."""
        with self.factory() as db:
            inputs = stored_inputs(db, session_id)
        ids: dict[str, int] = {}
        for kind, deps, uses in PIPELINE:
            ids[kind] = self.enqueue(
                session_id,
                kind,
                after=[ids[d] for d in deps],
                uses=[ids[u] for u in uses],
                params={"inputs": inputs},
            )
        return list(ids.values())

    def refresh(self, session_id: str) -> list[int]:
        """Queue the pipeline again if the session holds data its newest processing does
        not cover (stored after its inputs were fixed); the new jobs' ids, or none."""
        with self.factory() as db:
            job = latest_processing(db, session_id)
            if job is not None and "inputs" not in (job.params or {}):
                return []  # processed before jobs recorded their inputs: left as it is
            if is_current(latest_inputs(db, session_id), stored_inputs(db, session_id)):
                return []
        log.info("session %s: data stored after its processing; processing it again", session_id)
        return self.enqueue_pipeline(session_id)

    def catch_up(self) -> int:
        """Look again at every ended session that was processed: one that holds data its
        newest processing does not cover (its re-run was lost when the station stopped) is
        processed again. How many were looked at."""
        try:
            with self.factory() as db:
                sids = db.scalars(
                    select(Job.session_id)
                    .join(InspectionSession, InspectionSession.id == Job.session_id)
                    .where(Job.kind == "stitch", InspectionSession.status == SessionStatus.ended)
                    .distinct()
                ).all()
        except Exception:  # the database is away: the sessions' next data catches them up
            log.exception("could not look for sessions processed before their last data")
            return 0
        for sid in sids:
            self.mark_stale(sid)
        return len(sids)

    def mark_stale(self, session_id: str) -> None:
        """Data was stored into an ended session: :meth:`refresh` it once no more has come
        for ``settle_s`` (a robot's spool drains in a burst: one re-run for all of it)."""
        with self._stale_lock:
            self._stale[session_id] = time.monotonic()
        self._wake.set()

    def _refresh_settled(self) -> None:
        now = time.monotonic()
        with self._stale_lock:
            due = [sid for sid, t in self._stale.items() if now - t >= self.settle_s]
            for sid in due:
                del self._stale[sid]
        for sid in due:
            try:
                self.refresh(sid)
            except Exception:  # the session was deleted, the database is away: logged
                log.exception("session %s: could not queue its processing again", sid)

    def _new_pool(self) -> ProcessPoolExecutor:
        ctx = multiprocessing.get_context("spawn")
        return ProcessPoolExecutor(
            max_workers=self.workers, mp_context=ctx, initializer=init_worker
        )

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(timeout=1.0)
            self._wake.clear()
            try:
                self._refresh_settled()
                self._dispatch()
            except Exception:  # the dispatcher must outlive any one bad row
                log.exception("job dispatcher error")

    def _dispatch(self) -> None:
        with self.factory() as db:
            queued = list(
                db.scalars(select(Job).where(Job.state == JobState.queued).order_by(Job.id))
            )
            for job in queued:
                if self.send is None and (
                    job.id in self._running or len(self._running) >= self.workers
                ):
                    continue
                if self.send is not None and job.dispatched_at is not None:
                    continue
                deps = [db.get(Job, d) for d in job.params.get("after", [])]
                if any(
                    d is not None and d.state in (JobState.failed, JobState.cancelled) for d in deps
                ):
                    job.state = JobState.failed
                    job.error = "a job it depends on failed or was cancelled"
                    job.finished_at = utcnow()
                    db.commit()
                    continue
                if any(d is not None and d.state != JobState.done for d in deps):
                    continue
                used = [db.get(Job, u) for u in job.params.get("uses", [])]
                if any(u is not None and u.state not in leases.ENDED for u in used):
                    continue
                if self.send is None:
                    self._submit(job.id)
                else:
                    self._hand_over(db, job.id)
            if self.send is not None:
                self._hand_over_lost(db)

    def _hand_over(self, db: Session, job_id: int) -> None:
        """Give a job to the queue once (marked first; a crash in between is mended at the
        next start, and a second delivery finds the job claimed: :mod:`leases`)."""
        assert self.send is not None
        db.execute(update(Job).where(Job.id == job_id).values(dispatched_at=utcnow()))
        db.commit()
        self.send(job_id)

    def _hand_over_lost(self, db: Session) -> None:
        """Hand jobs out again whose worker stopped beating for a lease (killed, its machine
        gone) and that were not handed out since: a fresh attempt takes them over."""
        stale = leases.stale_before(self.lease_s)
        lost = db.scalars(
            select(Job.id).where(
                Job.state == JobState.running,
                or_(Job.heartbeat_at.is_(None), Job.heartbeat_at < stale),
                or_(Job.dispatched_at.is_(None), Job.dispatched_at < stale),
            )
        ).all()
        for job_id in lost:
            log.warning("job %d: its worker stopped answering; handing it out again", job_id)
            self._hand_over(db, job_id)

    @property
    def _run(self) -> Callable[[int], object]:
        return partial(
            run_job, database_url=self.database_url, data_dir=self.data_dir, lease_s=self.lease_s
        )

    def _submit(self, job_id: int) -> None:
        assert self._pool is not None
        try:
            future = self._pool.submit(self._run, job_id)
        except BrokenProcessPool:
            self._pool = self._new_pool()
            future = self._pool.submit(self._run, job_id)
        self._running[job_id] = future
        future.add_done_callback(lambda f, jid=job_id: self._finished(jid, f))

    def _finished(self, job_id: int, future: Future[None]) -> None:
        self._running.pop(job_id, None)
        exc = future.exception()
        if exc is not None:
            # run_job records its own failures; reaching here means the worker itself died.
            log.error("job %d: worker failed: %r", job_id, exc)
            leases.fail_unless_ended(self.factory, job_id, f"worker process failed: {exc!r}")
            if isinstance(exc, BrokenProcessPool):
                self._pool = self._new_pool()
        self._wake.set()
