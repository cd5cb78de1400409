"""What the running app holds (engine, ingest, hub, jobs); built in the lifespan."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from server.config import Settings
from server.jobs.runner import JobRunner
from server.limits import LoginThrottle, MalformedGuard, PasswordBudget
from server.link.group_commit import GroupCommit
from server.link.ingest import Ingest
from server.live.hub import LiveHub
from server.live.live_detect import LiveDetect
from server.live.live_map import LiveMap
from server.live.scenes import Scenes
from server.reports.coverage import QualityCache
from server.storage.files import SessionFiles


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
    quality: QualityCache = field(default_factory=QualityCache)  # frame sharpness, exposure
    coverage_memo: dict[str, Any] = field(default_factory=dict)  # session -> (key, coverage)
    logins: LoginThrottle = field(default_factory=LoginThrottle)  # wrong passwords per client
    malformed: MalformedGuard = field(default_factory=MalformedGuard)  # per robot
    passwords: PasswordBudget = field(default_factory=PasswordBudget)  # hashing, station-wide
