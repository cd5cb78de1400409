"""Shared fixtures: a real ground station on a free loopback port with its own data dir, and
one holding a simulated inspection, processed, that many tests read (``inspected``)."""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from server.config import Settings

# frames are searched for defects live only where a test asks for it (most tests record many
# frames; every station they start, in this process or as a subprocess, reads this default)
os.environ.setdefault("STEELSCAN_LIVE_DETECT", "false")
from robot_link.client import RobotLink
from robot_link.sim.inspection import InspectionSim, SimConfig
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


DATABASES = ("sqlite", "postgresql")


def databases_under_test() -> tuple[str, ...]:
    """The databases the stations of the tests run on: both, unless
    ``STEELSCAN_TEST_DATABASE`` names one."""
    one = os.environ.get("STEELSCAN_TEST_DATABASE")
    if one and one not in DATABASES:
        raise pytest.UsageError(f"STEELSCAN_TEST_DATABASE={one!r}: one of {DATABASES}")
    return (one,) if one else DATABASES


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """Every test whose station stores anything (it asks for ``database``, ``database_url``
    or ``settings``) runs once on SQLite and once on PostgreSQL; one marked
    ``one_database`` (a long browser run whose storage other tests cover on both) on the
    first of them only, the processed inspection (``inspected``) included."""
    one = metafunc.definition.get_closest_marker("one_database") is not None
    if "database" in metafunc.fixturenames:
        under_test = databases_under_test()
        metafunc.parametrize("database", under_test[:1] if one else under_test, indirect=True)
    if "inspected" in metafunc.fixturenames:
        under_test = databases_under_test()
        metafunc.parametrize(
            "inspected", under_test[:1] if one else under_test, indirect=True, scope="session"
        )


@pytest.fixture(scope="session")
def postgres() -> Iterator[Any]:
    """A PostgreSQL server of the test run's own (Debian's package, a temporary cluster)."""
    from bench.services import Postgres

    server = Postgres()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(scope="session")
def redis_server() -> Iterator[Any]:
    """A Redis server of the test run's own (Debian's package)."""
    from bench.services import Redis

    server = Redis()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture
def database(request: pytest.FixtureRequest) -> str:
    """Which database the test's station uses: "sqlite" or "postgresql"."""
    return str(request.param)


@pytest.fixture
def database_url(request: pytest.FixtureRequest, database: str, tmp_path: Path) -> str:
    """A fresh, empty database of that kind."""
    if database == "postgresql":
        return request.getfixturevalue("postgres").new_database()
    return f"sqlite:///{tmp_path / 'data' / 'steelscan.db'}"


@pytest.fixture
def settings(tmp_path: Path, database_url: str) -> Settings:
    return Settings(data_dir=tmp_path / "data", job_workers=1, database_url=database_url)


@pytest.fixture
def live_server(settings: Settings) -> Iterator[LiveServer]:
    token = make_token(settings)
    server = BackgroundServer(settings, free_port())
    server.start()
    try:
        yield LiveServer(server.url, settings, token, server.server.config.app)
    finally:
        server.stop()


# the simulator's true camera pose (x, y, yaw) of each frame of the processed inspection,
# in capture order, by session id: what placement on the structure is scored against
TRUE_CAMERA_POSES: dict[str, list[list[float]]] = {}
# and the true pose (4, 4, world) of its ToF sensor at each cloud, by session id and seq
TRUE_CLOUD_POSES: dict[str, dict[int, Any]] = {}


@pytest.fixture(scope="session")
def inspected(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[LiveServer, str]]:
    """A live server that holds one simulated inspection, fully processed (one per database:
    :func:`pytest_generate_tests` names them)."""
    data = tmp_path_factory.mktemp("reports") / "data"
    if request.param == "postgresql":
        database_url = request.getfixturevalue("postgres").new_database()
    else:
        database_url = f"sqlite:///{data / 'steelscan.db'}"
    settings = Settings(data_dir=data, database_url=database_url, job_workers=2, view3d=False)
    token = make_token(settings)
    server = BackgroundServer(settings, free_port())
    server.start()
    try:

        async def run() -> str:
            link = RobotLink(server.url, token)
            await link.start()
            try:
                result = await InspectionSim(
                    link, SimConfig(seed=11, lanes=2, time_scale=0.0)
                ).run()
                TRUE_CAMERA_POSES[str(result.session_id)] = result.frame_poses_true
                TRUE_CLOUD_POSES[str(result.session_id)] = result.cloud_poses_true
                return result.session_id
            finally:
                await link.close()

        sid = asyncio.run(run())
        deadline = time.monotonic() + 240
        while True:
            jobs = httpx.get(f"{server.url}/api/sessions/{sid}/jobs").json()
            if len(jobs) == 4 and all(j["state"] in ("done", "failed") for j in jobs):
                break
            assert time.monotonic() < deadline, jobs
            time.sleep(0.3)
        assert {j["kind"]: j["state"] for j in jobs} == {
            "stitch": "done",
            "map": "done",
            "detect": "done",
            "export": "done",
        }, jobs
        yield LiveServer(server.url, settings, token, server.server.config.app), sid
    finally:
        server.stop()
