"""What the running app holds (database, ingest, hub, jobs, the live views), opened and
closed as one: :meth:`AppState.open` and :meth:`AppState.close`."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from robot_link.protocol import Message
from server.config import Settings
from server.jobs.runner import JobRunner
from server.jobs.triggers import JobTriggers
from server.limits import LoginThrottle, MalformedGuard, PasswordBudget
from server.link.group_commit import GroupCommit
from server.link.ingest import Ingest, StoreResult
from server.live.foxglove import FoxgloveRelay
from server.live.hub import LiveHub
from server.live.live_detect import LiveDetect
from server.live.live_map import LiveMap
from server.live.relay import LiveRelay
from server.live.scenes import Scenes
from server.reports.coverage import QualityCache
from server.reports.surface_votes import SurfaceCache
from server.storage import db
from server.storage.files import SessionFiles
from server.storage.space import DiskReserve

log = logging.getLogger(__name__)

# what a stored robot message is handed to after its ACK: (robot name, message, result)
OnStored = Callable[[str, Message, StoreResult], Awaitable[None]]


@dataclass
class AppState:
    """Everything the routes share, kept on ``app.state.steelscan``."""

    settings: Settings
    engine: Engine
    factory: sessionmaker[Session]
    files: SessionFiles
    ingest: Ingest
    hub: LiveHub
    jobs: JobRunner
    writer: GroupCommit
    scenes: Scenes | None = None  # the 3D views (live and per session), when switched on
    live_detect: LiveDetect | None = None  # defects of each frame as it arrives, shown live
    live_map: LiveMap | None = None  # the map growing during a session, shown in the 3D view
    foxglove: FoxgloveRelay | None = None  # the live robots in Foxglove, when switched on
    # who is told of each stored robot message: the live views, then the jobs
    on_stored: list[OnStored] = field(default_factory=list)
    # who is shown a robot's live-only messages (VIDEO, COMMAND_ACK)
    on_live: list[Callable[[Message], None]] = field(default_factory=list)
    quality: QualityCache = field(default_factory=QualityCache)  # frame sharpness, exposure
    surface: SurfaceCache = field(default_factory=SurfaceCache)  # what clouds say of the surface
    coverage_memo: dict[str, Any] = field(default_factory=dict)  # session -> (key, coverage)
    logins: LoginThrottle = field(default_factory=LoginThrottle)  # wrong passwords per client
    malformed: MalformedGuard = field(default_factory=MalformedGuard)  # per robot
    passwords: PasswordBudget = field(default_factory=PasswordBudget)  # hashing, station-wide

    @classmethod
    def open(cls, settings: Settings, loop: asyncio.AbstractEventLoop) -> AppState:
        """Open the database (migrated to head), the data directory and every service the
        settings switch on, and start the jobs' dispatcher."""
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        url = settings.resolved_database_url()
        db.upgrade(url)
        engine = db.make_engine(url)
        factory = db.make_sessionmaker(engine)
        files = SessionFiles(settings.data_dir, fsync=settings.fsync)
        reserve = DiskReserve(settings.data_dir, settings.min_free_bytes)
        ingest = Ingest(factory, files, reserve, settings.max_live_sessions_per_robot)
        state = cls(
            settings,
            engine,
            factory,
            files,
            ingest,
            LiveHub(settings.live_queue),
            _job_runner(settings, factory, url),
            GroupCommit(ingest),
        )
        if settings.view3d:
            state.scenes = Scenes(settings.view3d_port)
            if settings.live_map:
                state.live_map = LiveMap(factory, state.scenes.live)
        if settings.live_detect:
            state.live_detect = LiveDetect(factory, state.hub, loop, settings.detect_method)
        relay = LiveRelay(state.hub, state.scenes, state.live_map, state.live_detect)
        state.on_stored = [relay.on_stored, JobTriggers(state.jobs, settings).on_stored]
        state.on_live = [relay.show_live]
        if settings.foxglove_port is not None:
            state.foxglove = FoxgloveRelay(settings.foxglove_host, settings.foxglove_port)
            state.on_stored.insert(1, state.foxglove.on_stored)
            state.on_live.append(state.foxglove.show_live)
        state.jobs.start()
        return state

    def close(self) -> None:
        """Stop every service, the last opened first."""
        self.passwords.executor.shutdown(wait=False)
        self.jobs.stop()
        self.writer.close()
        for service in (self.foxglove, self.live_map, self.live_detect, self.scenes):
            if service is not None:
                service.close()
        self.engine.dispose()


def _job_runner(settings: Settings, factory: sessionmaker[Session], url: str) -> JobRunner:
    """The jobs' dispatcher: the station's own worker processes, or a Celery queue."""
    send = None
    if settings.job_backend == "celery":
        from server.jobs.queue import CeleryQueue

        send = CeleryQueue(settings).send
    return JobRunner(
        factory,
        url,
        str(settings.data_dir.resolve()),
        settings.job_workers,
        defaults={"detect": {"method": settings.detect_method}},
        send=send,
        lease_s=settings.job_lease_s,
    )
