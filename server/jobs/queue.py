"""Jobs on Celery workers (``STEELSCAN_JOB_BACKEND=celery``, Redis as the broker).

The station sends a job's id (``steelscan.job``); a worker runs the same :func:`run_job` the
station's own pool runs, under the job's lease. Messages are acknowledged after the task
(``acks_late``) and put back when a worker process is lost mid-task, so another worker
takes the job; a delivery that finds a live attempt holding the job waits for its lease
(``retry``) and one that finds it ended does nothing: a job completes once. Parts of one
job go out as ``steelscan.part`` (:mod:`server.jobs.parts`). Only ids pass through the
broker; frames and results live in the data directory every worker mounts.

``steelscan worker`` starts a worker: :func:`run_worker`.
"""

from __future__ import annotations

import logging
import os
import socket
from functools import lru_cache
from typing import Any

from celery import Celery, group
from celery.signals import worker_process_init

from server.config import Settings
from server.jobs import leases
from server.jobs.parts import FolderFanout, help_with
from server.jobs.priority import yield_to_the_station
from server.jobs.worker import factory_for, run_job

log = logging.getLogger(__name__)

JOB_TASK = "steelscan.job"
PART_TASK = "steelscan.part"


def make_app(broker_url: str, lease_s: float = leases.LEASE_S) -> Celery:
    """The Celery application (the station sends with it; ``steelscan worker`` runs it)."""
    app = Celery("steelscan", broker=broker_url, set_as_current=False)
    app.conf.update(
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        task_ignore_result=True,  # results are rows and files, not broker messages
        task_serializer="json",
        accept_content=["json"],
        broker_connection_retry_on_startup=True,
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
        # an unacknowledged task comes back after this long even if its worker is only slow:
        # the lease makes that second delivery wait, never run twice
        broker_transport_options={"visibility_timeout": max(3600.0, 10 * lease_s)},
        task_default_queue="steelscan",
    )
    app.task(name=JOB_TASK, bind=True, max_retries=None)(_job_task)
    app.task(name=PART_TASK)(_part_task)
    return app


@lru_cache(maxsize=1)
def _settings() -> Settings:
    return Settings()


@lru_cache(maxsize=1)
def worker_app() -> Celery:
    """The worker's application, configured from its own STEELSCAN_* settings."""
    s = _settings()
    return make_app(s.broker_url, s.job_lease_s)


def _job_task(self: Any, job_id: int) -> str:
    s = _settings()
    app = self.app

    def ask(jid: int, name: str, helpers: int) -> None:
        group(app.signature(PART_TASK, args=[jid, name]) for _ in range(helpers)).apply_async()

    outcome = run_job(
        job_id,
        s.resolved_database_url(),
        str(s.data_dir.resolve()),
        worker=f"{self.request.hostname}:{os.getpid()}",
        lease_s=s.job_lease_s,
        threads=s.worker_threads,
        fanout=FolderFanout(ask, s.job_fanout, s.job_lease_s),
    )
    if outcome == "held":  # a delivery while a live attempt holds it: try when its lease ends
        wait = leases.holder_alive_for(
            factory_for(s.resolved_database_url()), job_id, s.job_lease_s
        )
        raise self.retry(countdown=1.0 + (wait or 0.0))
    return outcome


def _part_task(job_id: int, name: str) -> int:
    s = _settings()
    done = help_with(s.data_dir.resolve(), name, s.job_lease_s)
    log.info("job %d: %d parts of %s done here", job_id, done, name)
    return done


class CeleryQueue:
    """The station's side: hands job ids to the broker."""

    def __init__(self, settings: Settings) -> None:
        self.app = make_app(settings.broker_url, settings.job_lease_s)

    def send(self, job_id: int) -> None:
        """Queue one job for the workers."""
        self.app.send_task(JOB_TASK, args=[job_id])


@worker_process_init.connect
def _init_worker_process(**_: Any) -> None:
    """Each worker process: idle priority (below the live link of a station on the same
    machine), arrays on the heap, and ``worker_threads`` threads per library (a process per
    core scales: ``--concurrency``)."""
    from server.process.allocator import keep_arrays_on_heap

    limit_threads(_settings().worker_threads)
    yield_to_the_station()
    keep_arrays_on_heap()


def limit_threads(threads: int) -> None:
    """Keep this process's libraries to ``threads`` threads each: OpenCV's pool and Open3D's
    (oneTBB, which no environment variable bounds; its ICP took 1.7 cores of a 2-core
    machine unbounded)."""
    import cv2
    import open3d as o3d

    cv2.setNumThreads(threads)
    o3d.utility.set_max_threads(threads)


def ping_worker(timeout_s: float = 3.0) -> bool:
    """Whether a worker on this host answers through the broker (a container's health)."""
    host = socket.gethostname()
    replies = worker_app().control.ping(timeout=timeout_s)
    return any(name.endswith(f"@{host}") for reply in replies for name in reply)


def run_worker(concurrency: int, loglevel: str = "INFO") -> None:
    """Run a worker in this process until it is stopped (SIGTERM: warm shutdown). The
    worker's own process (broker, pool and results) yields to the station as its job
    processes do: at normal priority it took a tenth of a core beside a busy job."""
    yield_to_the_station()
    app = worker_app()
    app.worker_main(
        [
            "worker",
            f"--concurrency={concurrency}",
            f"--loglevel={loglevel}",
            "--pool=prefork",
            "-Q",
            "steelscan",
            "-n",
            f"steelscan-{os.getpid()}@%h",
            "--without-gossip",
            "--without-mingle",
        ]
    )
