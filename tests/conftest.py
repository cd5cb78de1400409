"""Shared fixtures: a real ground station on a free loopback port with its own data dir."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from server.config import Settings

# frames are searched for defects live only where a test asks for it (most tests record many
# frames; every station they start, in this process or as a subprocess, reads this default)
os.environ.setdefault("STEELSCAN_LIVE_DETECT", "false")
from server.link.robots import create_robot
from server.loopback import BackgroundServer, free_port
from server.storage.db import make_engine, make_sessionmaker, upgrade


@dataclass
class LiveServer:
    url: str
    settings: Settings
    token: str
    app: Any = None  # the FastAPI app, for looking at its state


def make_token(settings: Settings, name: str = "test-robot") -> str:
    """Register a robot in the settings' database and return its token."""
    url = settings.resolved_database_url()
    upgrade(url)
    engine = make_engine(url)
    try:
        return create_robot(make_sessionmaker(engine), name)
    finally:
        engine.dispose()


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return Settings(data_dir=tmp_path / "data", job_workers=1)


@pytest.fixture
def live_server(settings: Settings) -> Iterator[LiveServer]:
    token = make_token(settings)
    server = BackgroundServer(settings, free_port())
    server.start()
    try:
        yield LiveServer(server.url, settings, token, server.server.config.app)
    finally:
        server.stop()
