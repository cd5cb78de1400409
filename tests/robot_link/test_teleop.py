"""The teleoperated simulated robot against the real server, driven through the browsers'
websocket: it moves while commands arrive, stops by itself within the dead-man bound when
they stop, on e-stop, and when its driver's page goes away; one operator drives, others watch."""

from __future__ import annotations

import json
import struct
import time
from collections.abc import Iterator

import pytest
from websockets.sync.client import ClientConnection

from robot_link.protocol import DRIVE_HOLD_S
from robot_link.sim.teleop import TeleopRobot, start_teleop_robot
from server.config import Settings
from tests.conftest import LiveServer
from tests.operator_ws import browser, events, wait_for_robot

DEADMAN_BOUND_MS = 300


@pytest.fixture
def settings(tmp_path) -> Settings:  # type: ignore[no-untyped-def]
    return Settings(data_dir=tmp_path / "data", job_workers=1, auto_process=False, view3d=False)


@pytest.fixture
def robot(live_server: LiveServer) -> Iterator[TeleopRobot]:
    r = start_teleop_robot(live_server.url, live_server.token, seed=3)
    yield r
    r.stop(timeout_s=60)


def drive(ws: ClientConnection, sid: str, seconds: float, v: float = 0.1) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        ws.send(
            json.dumps(
                {
                    "session_id": sid,
                    "cmd": "drive",
                    "args": {"linear_mps": v, "angular_radps": 0.0, "sent_ms": time.time() * 1000},
                }
            )
        )
        time.sleep(0.05)


def test_drives_while_commanded_and_stops_within_the_deadman_bound(
    live_server: LiveServer, robot: TeleopRobot
) -> None:
    with browser(live_server) as ws:
        wait_for_robot(ws, robot.session_id)
        x0 = float(robot.sim.robot.odom[0])
        drive(ws, robot.session_id, 1.0)
        assert robot.sim.v == pytest.approx(0.1)
        time.sleep(DEADMAN_BOUND_MS / 1000)  # no more commands: the robot stops by itself
        assert robot.sim.v == 0.0
        moved = float(robot.sim.robot.odom[0]) - x0
        assert 0.07 < moved < 0.14  # about a second at 0.1 m/s
        assert (
            robot.sim.log.deadman_stops_ms
            and max(robot.sim.log.deadman_stops_ms) <= DEADMAN_BOUND_MS
        )
        assert min(robot.sim.log.deadman_stops_ms) >= DRIVE_HOLD_S * 1000
        assert (
            robot.sim.log.command_latency_ms
            and sorted(robot.sim.log.command_latency_ms)[len(robot.sim.log.command_latency_ms) // 2]
            < 50
        )
        # live video and telemetry reach the browser
        video, telemetry = 0, None
        for e in events(ws, time.monotonic() + 2):
            if isinstance(e, bytes):
                header = json.loads(e[4 : 4 + struct.unpack("<I", e[:4])[0]])
                video += bool(header.get("video")) and e[
                    4 + struct.unpack("<I", e[:4])[0] :
                ].startswith(b"\xff\xd8")
            elif e.get("type") == "telemetry" and e["session_id"] == robot.session_id:
                telemetry = e["data"]
        assert video >= 10 and telemetry is not None
        assert telemetry["mode"] == "teleop" and telemetry["drive"]["linear_mps"] == 0.0


def test_estop_holds_until_resume(live_server: LiveServer, robot: TeleopRobot) -> None:
    with browser(live_server) as ws:
        wait_for_robot(ws, robot.session_id)
        drive(ws, robot.session_id, 0.3)
        ws.send(json.dumps({"session_id": robot.session_id, "cmd": "estop"}))
        time.sleep(0.2)
        assert robot.sim.v == 0.0 and robot.sim.estopped
        drive(ws, robot.session_id, 0.3)
        assert robot.sim.v == 0.0 and any("emergency stop" in r for r in robot.sim.log.refused)
        ws.send(json.dumps({"session_id": robot.session_id, "cmd": "resume"}))
        time.sleep(0.2)
        drive(ws, robot.session_id, 0.2)
        assert robot.sim.v > 0


def test_one_operator_drives_others_watch_and_the_robot_stops_when_the_driver_leaves(
    live_server: LiveServer, robot: TeleopRobot
) -> None:
    with browser(live_server) as watcher:
        wait_for_robot(watcher, robot.session_id)
        driver = browser(live_server)
        wait_for_robot(driver, robot.session_id)
        drive(driver, robot.session_id, 0.3)
        # the second browser may not drive, but may stop
        watcher.send(
            json.dumps(
                {"session_id": robot.session_id, "cmd": "drive", "args": {"linear_mps": -0.1}}
            )
        )
        refusal = next(
            e
            for e in events(watcher, time.monotonic() + 5)
            if isinstance(e, dict) and e.get("type") == "command_result"
        )
        assert not refusal["ok"] and "driven by" in refusal["error"]
        # the driver's page goes away mid-drive: the station stops the robot at once
        drive(driver, robot.session_id, 0.3)
        driver.close()
        t0 = time.monotonic()
        while robot.sim.v != 0.0:
            assert time.monotonic() - t0 < DEADMAN_BOUND_MS / 1000
            time.sleep(0.005)
        control = [
            e
            for e in events(watcher, time.monotonic() + 1)
            if isinstance(e, dict) and e.get("type") == "control"
        ]
        assert control and control[-1]["holder"] is None
        # now the watcher may take over
        drive(watcher, robot.session_id, 0.2)
        assert robot.sim.v < 0 or robot.sim.log.drive_commands > 0


def test_at_the_plate_edge_forward_is_blocked_and_the_telemetry_says_why(
    live_server: LiveServer, robot: TeleopRobot
) -> None:
    """Commanded forward at the plate's far end: the robot holds still, its telemetry gives
    the actual speed (0), the commanded one and the sensors that block it; reverse still
    drives."""
    sim = robot.sim
    length_m, width_m = sim.structure.plate_size_m
    sim.robot.pose[:] = (length_m - 0.02, width_m / 2, 0.0)  # the front sensors overhang
    with browser(live_server) as ws:
        wait_for_robot(ws, robot.session_id)
        drive(ws, robot.session_id, 0.6)
        blocked = None
        for e in events(ws, time.monotonic() + 1.0):
            if isinstance(e, dict) and e.get("type") == "telemetry":
                if e["data"]["drive"]["commanded_linear_mps"] > 0:
                    blocked = e["data"]
        assert blocked is not None
        assert blocked["drive"]["linear_mps"] == 0.0
        assert blocked["drive"]["blocked_by"] == ["front_left", "front_right"]
        assert blocked["edge_action"] == "block_forward"
        assert max(abs(v) for v in blocked["wheel_speed_mps"]) < 1e-6
        assert sim.robot.pose[0] == pytest.approx(length_m - 0.02, abs=1e-3)
        drive(ws, robot.session_id, 0.6, v=-0.1)  # reverse, away from the edge
        assert sim.robot.pose[0] < length_m - 0.04
