"""Robots over REST (admin role) on the real server: register one (its token shown once)
that then connects, list them with their sessions, revoke one so it cannot connect."""

from __future__ import annotations

import uuid

import httpx
import pytest
from websockets.exceptions import InvalidStatus

from robot_link.protocol import decode_message
from tests.conftest import LiveServer
from tests.server.helpers import robot_ws, start


def test_register_list_and_revoke(live_server: LiveServer) -> None:
    url = f"{live_server.url}/api/robots"
    r = httpx.post(url, json={"name": "crawler-2"})
    assert r.status_code == 201
    token = r.json()["token"]
    assert token.startswith("ssr_")
    assert httpx.post(url, json={"name": "crawler-2"}).status_code == 409
    with robot_ws(live_server, token) as ws:  # the new robot connects and records a session
        ws.send(start(uuid.uuid4()))
        decode_message(ws.recv(timeout=10))
    rows = {r["name"]: r for r in httpx.get(url).json()}
    assert rows["crawler-2"]["sessions"] == 1 and not rows["crawler-2"]["revoked"]
    assert rows["test-robot"]["sessions"] == 0
    assert all("token" not in r for r in rows.values())  # never shown again
    assert httpx.delete(f"{url}/crawler-2").status_code == 204
    assert httpx.get(url).json()[0]["revoked"]
    with pytest.raises(InvalidStatus):
        robot_ws(live_server, token)
    assert httpx.delete(f"{url}/nothing").status_code == 404
    sessions = httpx.get(f"{live_server.url}/api/sessions").json()["data"]
    assert sessions[0]["robot_name"] == "crawler-2"  # its sessions stay under its name
