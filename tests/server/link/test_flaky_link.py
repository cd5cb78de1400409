"""The whole inspection over a link that cuts, stalls and delays at random: nothing lost,
nothing stored twice."""

import asyncio

import httpx
import pytest

from robot_link.client import RobotLink
from robot_link.sim.inspection import InspectionSim, SimConfig
from tests.conftest import LiveServer
from tests.fault_proxy import FaultProxy

pytestmark = pytest.mark.slow  # an end-to-end run


def test_inspection_through_a_faulty_link_stores_every_frame_once(live_server: LiveServer) -> None:
    port = int(live_server.url.rsplit(":", 1)[1])

    async def run() -> tuple[dict, FaultProxy, RobotLink]:
        proxy = FaultProxy(port, seed=3, cut_probability=0.06, stall_probability=0.04)
        proxy_port = await proxy.start()
        link = RobotLink(f"http://127.0.0.1:{proxy_port}", live_server.token, max_backoff_s=0.3)
        await link.start()
        try:
            result = await InspectionSim(link, SimConfig(lanes=2, time_scale=0, seed=5)).run()
        finally:
            await link.close()
            await proxy.stop()
        return result.summary(), proxy, link

    summary, proxy, link = asyncio.run(run())
    assert proxy.cuts >= 2 and proxy.stalls >= 2  # the link really was bad
    assert link.stats.reconnects >= 2 and link.stats.resent >= 1
    session = (
        httpx.get(f"{live_server.url}/api/sessions/{summary['session_id']}")
        .raise_for_status()
        .json()
    )
    # every frame stored, none twice (unique per seq)
    assert session["frames"] == summary["frames_sent"] > 0
    assert session["clouds"] == summary["clouds_sent"] > 0
