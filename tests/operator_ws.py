"""An operator's browser websocket (``/ws/live``) to a live station, for tests that drive
a teleoperated robot as the dashboard does."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

from websockets.sync.client import ClientConnection, connect

from tests.conftest import LiveServer


def browser(live_server: LiveServer) -> ClientConnection:
    return connect(
        live_server.url.replace("http", "ws") + "/ws/live", max_size=2**22, close_timeout=0.5
    )


def events(ws: ClientConnection, until: float) -> Iterator[dict | bytes]:
    while time.monotonic() < until:
        try:
            item = ws.recv(timeout=max(0.01, until - time.monotonic()))
        except TimeoutError:
            return
        yield item if isinstance(item, bytes) else json.loads(item)


def wait_for_robot(ws: ClientConnection, sid: str) -> None:
    for e in events(ws, time.monotonic() + 20):
        if (
            isinstance(e, dict)
            and e.get("type") == "robot"
            and e["session_id"] == sid
            and e["connected"]
        ):
            return
    raise AssertionError("the robot never attached")
