"""The live 3D map refines where the coverage map places frames: while no mosaic exists,
each frame moves by the live map's registration of the odometry at the nearest cloud, which
brings it closer to where the camera truly was; with the camera's steps between the clouds
in its graph, to about a millimetre."""

from __future__ import annotations

import asyncio
import time

import httpx
import numpy as np
import pytest

from robot_link.client import RobotLink
from robot_link.sim.inspection import InspectionSim, SimConfig, SimResult
from server.config import Settings
from tests.conftest import LiveServer


@pytest.fixture
def settings(settings: Settings) -> Settings:
    return settings.model_copy(update={"auto_process": False})


def test_the_live_map_refines_frame_placement(live_server: LiveServer) -> None:
    async def run() -> SimResult:
        link = RobotLink(live_server.url, live_server.token)
        await link.start()
        try:
            return await InspectionSim(link, SimConfig(seed=21, lanes=2, time_scale=3.0)).run()
        finally:
            await link.close()

    result = asyncio.run(run())
    sid = str(result.session_id)
    live_map = live_server.app.state.steelscan.live_map
    clouds = httpx.get(f"{live_server.url}/api/sessions/{sid}/clouds", params={"limit": 1}).json()
    deadline = time.monotonic() + 90
    while len(live_map.corrections.get(sid, [])) + live_map.skipped < clouds["count"]:
        assert time.monotonic() < deadline, "the live map did not catch up"
        time.sleep(0.2)
    cov = httpx.get(f"{live_server.url}/api/sessions/{sid}/coverage", params={"grid": False}).json()
    assert {f["placed_by"] for f in cov["frames"]} == {"live map"}
    frames = httpx.get(
        f"{live_server.url}/api/sessions/{sid}/frames", params={"limit": 1000}
    ).json()
    mount = httpx.get(f"{live_server.url}/api/sessions/{sid}").json()["calibration"]["camera"][
        "T_robot_camera"
    ][0]
    truth = np.array(result.frame_poses_true)[:, :2]
    placed = np.array([np.mean(f["footprint"], axis=0) for f in cov["frames"]])
    odometry = np.array(
        [
            [
                f["pose_x"] + mount * np.cos(f["pose_yaw"]),
                f["pose_y"] + mount * np.sin(f["pose_yaw"]),
            ]
            for f in frames["data"]
        ]
    )
    err_live = np.linalg.norm(placed - truth, axis=1)
    err_odometry = np.linalg.norm(odometry - truth, axis=1)
    print(
        f"live map placement: mean {err_live.mean() * 1000:.1f} mm, worst {err_live.max() * 1000:.1f} mm; "
        f"odometry mean {err_odometry.mean() * 1000:.1f} mm, worst {err_odometry.max() * 1000:.1f} mm; "
        f"{live_map.skipped} of {clouds['count']} clouds skipped"
    )
    assert err_live.mean() < err_odometry.mean()
    # the frames' steps in the live graph: the ToF and the odometry alone leave 4 mm
    assert err_live.mean() < 2e-3, err_live.mean()
