"""Fixtures of the server tests: one simulated inspection, processed, that the report,
coverage and defect tests read (one per database and test run: it takes a simulated
inspection and the whole pipeline)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator

import httpx
import pytest

from robot_link.client import RobotLink
from robot_link.sim.inspection import InspectionSim, SimConfig
from server.config import Settings
from server.loopback import BackgroundServer, free_port
from tests.conftest import LiveServer, databases_under_test, make_token

# the simulator's true camera pose (x, y, yaw) of each frame of the processed inspection,
# in capture order, by session id: what placement on the structure is scored against
TRUE_CAMERA_POSES: dict[str, list[list[float]]] = {}


@pytest.fixture(scope="session", params=databases_under_test())
def inspected(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[LiveServer, str]]:
    """A live server that holds one simulated inspection, fully processed (one per database)."""
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
