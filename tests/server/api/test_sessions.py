"""The sessions resource against the real server: a list that can be searched and narrowed
by status, each session with its robot, its duration on the robot's clock, and as operator
the users who drove it."""

from __future__ import annotations

import json
import time
import uuid

import httpx
import pytest
from websockets.sync.client import connect

from robot_link.protocol import Message, MessageType, encode_message
from server.config import Settings
from tests.conftest import LiveServer
from tests.server.helpers import robot_ws


@pytest.fixture
def settings(settings: Settings) -> Settings:
    return settings.model_copy(update={"auto_process": False, "view3d": False})


def record(server: LiveServer, structure: str, location: str, t0: float, seconds: float) -> str:
    """A session of telemetry from ``t0`` to ``t0 + seconds`` on the robot's clock, ended."""
    sid = uuid.uuid4()
    with robot_ws(server) as ws:
        messages = [
            Message(
                MessageType.SESSION_START,
                sid,
                1,
                t0,
                {"structure": structure, "operator": "robot-default", "location": location},
            ),
            Message(MessageType.TELEMETRY, sid, 2, t0, {"battery_v": {"main": 12.4}}),
            Message(MessageType.TELEMETRY, sid, 3, t0 + seconds, {"battery_v": {"main": 12.3}}),
            Message(MessageType.SESSION_END, sid, 4, t0 + seconds, {}),
        ]
        for m in messages:
            ws.send(encode_message(m))
            ws.recv(timeout=10)
    return str(sid)


def listing(server: LiveServer, **params: str) -> dict:
    return httpx.get(f"{server.url}/api/sessions", params=params).raise_for_status().json()


def test_search_status_duration_and_robot(live_server: LiveServer) -> None:
    t0 = time.time() - 3600
    box = record(live_server, "Box girder span 3", "Elm St bridge", t0, 725.0)
    truss = record(live_server, "Truss chord L4-L5", "Rail yard", t0 + 10, 61.5)
    rows = listing(live_server)["data"]
    assert {r["id"] for r in rows} == {box, truss}
    by_id = {r["id"]: r for r in rows}
    assert by_id[box]["duration_s"] == pytest.approx(725.0, abs=0.01)  # robot clock, not arrival
    assert by_id[truss]["duration_s"] == pytest.approx(61.5, abs=0.01)
    assert by_id[box]["robot_name"] == "test-robot"
    # every word must match some field, case-insensitively; ids and robot names count
    assert [r["id"] for r in listing(live_server, q="box ELM")["data"]] == [box]
    assert listing(live_server, q="box rail")["count"] == 0
    assert [r["id"] for r in listing(live_server, q=truss[:8])["data"]] == [truss]
    assert listing(live_server, q="test-robot")["count"] == 2
    assert listing(live_server, q="100%")["count"] == 0  # LIKE wildcards are literal
    assert listing(live_server, q="L4_L5")["count"] == 0
    assert listing(live_server, status="ended")["count"] == 2
    assert listing(live_server, status="live")["count"] == 0
    bad = httpx.get(f"{live_server.url}/api/sessions", params={"status": "gone"})
    assert bad.status_code == 422
    # the report gives the same duration
    report = httpx.get(f"{live_server.url}/api/sessions/{box}/report.json").json()
    assert report["summary"]["duration_s"] == pytest.approx(725.0, abs=0.01)


def test_the_users_who_drive_a_robot_become_the_sessions_operator(
    live_server: LiveServer,
) -> None:
    sid = uuid.uuid4()
    with robot_ws(live_server) as robot:
        robot.send(
            encode_message(
                Message(
                    MessageType.SESSION_START,
                    sid,
                    1,
                    time.time(),
                    {"structure": "girder", "operator": "robot-default"},
                )
            )
        )
        robot.recv(timeout=10)
        url = live_server.url.replace("http", "ws") + "/ws/live"
        with connect(url) as browser:
            browser.send(json.dumps({"type": "control", "session_id": str(sid), "action": "take"}))
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                event = json.loads(browser.recv(timeout=10))
                if event.get("type") == "command_result" and event.get("cmd") == "take":
                    assert event["ok"]
                    break
        session = httpx.get(f"{live_server.url}/api/sessions/{sid}").json()
        assert session["operator"] == "anonymous"  # no accounts: the anonymous admin drove it


def test_text_a_database_cannot_store_is_refused_with_a_clear_error(
    live_server: LiveServer,
) -> None:
    """A NUL character (PostgreSQL's text cannot hold one) in a search, a name or a note is
    a 422 that says so, on either database; nothing reaches the database half-written."""
    url = live_server.url
    sid = record(live_server, "girder 7", "span 2", 0.0, 10.0)
    r = httpx.get(f"{url}/api/sessions", params={"q": "gird\x00er"})
    assert r.status_code == 422 and "NUL" in r.text
    r = httpx.patch(f"{url}/api/sessions/{sid}", json={"notes": "crack at\x00 weld"})
    assert r.status_code == 422 and "NUL" in r.text
    assert httpx.get(f"{url}/api/sessions/{sid}").json()["notes"] in ("", None)
    r = httpx.post(f"{url}/api/robots", json={"name": "crawler\x00"})
    assert r.status_code == 422 and "NUL" in r.text
    assert [
        s["id"] for s in httpx.get(f"{url}/api/sessions", params={"q": "girder"}).json()["data"]
    ] == [sid]
