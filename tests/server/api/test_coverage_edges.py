"""The surface in view ends at the plate's edges: a teleoperated robot turned beside the
plate's edge puts part of a frame past it (the camera sits behind the robot's centre); that
part is neither imaged surface nor a hole, and the surface in view stays on the plate."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

import httpx
import numpy as np
import pytest

from processing.coverage import coverage_map
from robot_link.sim.teleop import TeleopRobot, start_teleop_robot
from server.config import Settings
from tests.conftest import LiveServer
from tests.operator_ws import browser, wait_for_robot

SEED = 5


@pytest.fixture
def settings(tmp_path, database_url) -> Settings:  # type: ignore[no-untyped-def]
    return Settings(
        data_dir=tmp_path / "data",
        database_url=database_url,
        job_workers=1,
        auto_process=False,
        view3d=False,
        live_map=False,
    )


@pytest.fixture
def robot(live_server: LiveServer) -> Iterator[TeleopRobot]:
    r = start_teleop_robot(live_server.url, live_server.token, seed=SEED)
    yield r
    r.stop(timeout_s=60)


def turn(ws, sid: str, seconds: float, w: float) -> None:  # type: ignore[no-untyped-def]
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        args = {"linear_mps": 0.0, "angular_radps": w, "sent_ms": time.time() * 1000}
        ws.send(json.dumps({"session_id": sid, "cmd": "drive", "args": args}))
        time.sleep(0.05)


def on_plate_area(
    footprints: list[list[list[float]]], plate: tuple[float, float]
) -> tuple[float, float]:
    """The area the footprints cover on the plate and off it (the structure's frame is the
    session's world frame: the simulated robot starts on its datum)."""
    cov = coverage_map([np.array(f) for f in footprints], [True] * len(footprints))
    r, c = np.nonzero(cov.imaged)
    x = cov.origin_m[0] + (c + 0.5) * cov.cell_m
    y = cov.origin_m[1] + (r + 0.5) * cov.cell_m
    on = (x >= 0) & (x <= plate[0]) & (y >= 0) & (y <= plate[1])
    return float(on.sum()) * cov.cell_m**2, float((~on).sum()) * cov.cell_m**2


def test_a_frame_past_the_edge_adds_no_surface_and_no_hole(
    live_server: LiveServer, robot: TeleopRobot
) -> None:
    sid = robot.session_id
    plate = robot.sim.structure.plate_size_m
    with browser(live_server) as ws:
        wait_for_robot(ws, sid)
        ws.send(json.dumps({"session_id": sid, "cmd": "capture"}))
        time.sleep(0.5)
        turn(ws, sid, 2.0, 0.8)  # a right turn: the heading swings to +y, the camera to -y
        time.sleep(0.5)
        ws.send(json.dumps({"session_id": sid, "cmd": "capture"}))
        time.sleep(1.0)
    url = f"{live_server.url}/api/sessions/{sid}/coverage"
    cov = httpx.get(url).raise_for_status().json()
    feet = [f["footprint"] for f in cov["frames"]]
    lowest = min(p[1] for f in feet for p in f)
    assert lowest < -0.03, "a frame reaches past the plate's y = 0 edge"
    on, off = on_plate_area(feet, plate)
    # the part past the edge is not imaged: what is left is the part on the plate, but for
    # the tiles the edge cuts (a frame's exposure is judged per tile, 1/48 of its height)
    assert off > 0.1 * on
    assert 0.97 * on <= cov["area_imaged_m2"] <= on + 0.1 * off
    assert cov["area_surface_m2"] <= on + 0.1 * off
    for h in cov["holes"]:
        assert h["y_m"] >= 0, h
