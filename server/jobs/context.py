"""What a job body gets (:class:`JobContext`) and the helpers every job shares."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
from sqlalchemy import Select
from sqlalchemy.orm import Session, sessionmaker

from server.jobs import leases
from server.jobs.inputs import rows_of
from server.jobs.outputs import staging_dir
from server.storage.files import SessionFiles, write_atomic
from server.storage.models import InspectionSession

Part = Callable[[SessionFiles, Any, Any], Any]  # (files, shared, item) -> result
Finisher = Callable[[Session], None]  # database work done in the transaction that ends a job


class JobLost(Exception):
    """The attempt no longer holds its job: cancelled, or taken over by another worker."""


class Fanout(Protocol):
    """Runs a job's independent parts on other workers as well (:mod:`server.jobs.parts`)."""

    def __call__(
        self, ctx: JobContext, fn: Part, shared: Any, items: Sequence[Any]
    ) -> list[Any]: ...


@dataclass
class JobContext:
    """What a job body gets: its row's ids and parameters, the database and the data
    directory; the attempt that holds the job, the threads it may use and, on a job queue,
    the way to spread its parts over other workers.

    A job reads earlier jobs' results from :meth:`results_dir` and writes its own into
    :meth:`output_dir`; its database writes are :meth:`on_finish` work. Both become the
    session's only in the transaction that finishes the job while this attempt holds it
    (:mod:`server.jobs.outputs`), so a cancelled or taken-over attempt changes nothing."""

    job_id: int
    session_id: str
    factory: sessionmaker[Session]
    files: SessionFiles
    params: dict[str, Any] = field(default_factory=dict)
    attempt: int = 0
    threads: int = 2
    fanout: Fanout | None = None
    lost: threading.Event = field(default_factory=threading.Event)
    finishers: list[Finisher] = field(default_factory=list)

    def progress(self, fraction: float, message: str = "") -> None:
        """Record progress (0-1) and a short message; raises :class:`JobLost` when the
        attempt no longer holds the job, so the body stops there."""
        self.check()
        if not leases.beat(
            self.factory, self.job_id, self.attempt, progress=fraction, message=message
        ):
            self.lost.set()
            raise JobLost(self.job_id)

    def check(self) -> None:
        """Raise :class:`JobLost` if the heartbeat found the job cancelled or taken over."""
        if self.lost.is_set():
            raise JobLost(self.job_id)

    def map(self, fn: Part, shared: Any, items: Sequence[Any]) -> list[Any]:
        """``[fn(files, shared, item) for item in items]``, in order: spread over the job
        queue's workers when there is one, else on this process's threads. ``fn`` is a
        module-level function; ``shared`` and the items are picklable and small (ids and
        paths: a part reads what it needs from the data directory)."""
        if self.fanout is not None and len(items) > 1:
            return self.fanout(self, fn, shared, items)
        with ThreadPoolExecutor(max_workers=max(1, self.threads)) as pool:
            return list(pool.map(lambda item: fn(self.files, shared, item), items))

    def session(self) -> InspectionSession:
        """The job's session row."""
        with self.factory() as db:
            s = db.get(InspectionSession, self.session_id)
            if s is None:
                raise ValueError(f"session {self.session_id} no longer exists")
            return s

    def rows(self, model: Any) -> Select[Any]:
        """SELECT of the session's frames, clouds or telemetry (``model``) that this job
        reads: those stored when it was queued (:mod:`server.jobs.inputs`), in seq order."""
        return rows_of(model, self.session_id, self.params.get("inputs"))

    def results_dir(self) -> Path:
        """Folder of this session's results (earlier jobs' files; read only)."""
        d = self.files.results_dir(self.session_id)
        d.mkdir(parents=True, exist_ok=True)
        return d

    def output_dir(self) -> Path:
        """Folder this attempt writes its result files into (its staging folder: they move
        into :meth:`results_dir` when the job finishes)."""
        d = staging_dir(self.results_dir(), self.job_id, self.attempt)
        d.mkdir(exist_ok=True)
        return d

    def on_finish(self, fn: Finisher) -> None:
        """Do ``fn(db)`` in the transaction that records the job done (only if this attempt
        still holds it then)."""
        self.finishers.append(fn)

    def store(self, db: Session) -> None:
        """The job's :meth:`on_finish` work, in order (called by the finishing transaction)."""
        for fn in self.finishers:
            fn(db)


class Heartbeat:
    """Renews a running job's lease every ``interval_s`` on a thread of its own, so that a
    long stretch without progress reports does not look like a lost worker; sets the
    context's ``lost`` when the job was cancelled or taken over."""

    def __init__(self, ctx: JobContext, interval_s: float) -> None:
        self.ctx, self.interval_s = ctx, interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="job-heartbeat", daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                held = leases.beat(self.ctx.factory, self.ctx.job_id, self.ctx.attempt)
            except Exception:  # the database is away for a moment: the next beat tries again
                continue
            if not held:
                self.ctx.lost.set()
                return

    def __enter__(self) -> Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=10)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an image as PNG, atomically."""
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"could not encode {path.name}")
    write_atomic(path, buf.tobytes())


def params_record(params: Any) -> dict[str, Any]:
    """A parameters dataclass as JSON-ready data (for the report's parameter table)."""
    return json.loads(json.dumps(asdict(params), default=str))
