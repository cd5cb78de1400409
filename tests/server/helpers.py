"""What many server tests share: a robot's messages on its websocket, the station's ingest
on its own, waiting for jobs, accounts, an empty session, the command line."""

from __future__ import annotations

import subprocess
import sys
import time
import uuid

import httpx
from websockets.sync.client import connect

from robot_link.protocol import Message, MessageType, decode_message, encode_message
from server.api.accounts import create_user
from server.storage.db import make_engine, make_sessionmaker, upgrade
from server.storage.models import Role
from tests.conftest import LiveServer
from tests.media import jpeg

JPEG = jpeg(640, 480)


def ws_url(server: LiveServer) -> str:
    return server.url.replace("http://", "ws://") + "/ws/robot"


def robot_ws(server: LiveServer, token: str | None = None, **kwargs: object):  # type: ignore[no-untyped-def]
    """A robot's websocket to the station (``token``: another robot's)."""
    headers = {"Authorization": f"Bearer {token or server.token}"}
    return connect(ws_url(server), additional_headers=headers, **kwargs)  # type: ignore[arg-type]


def msg(sid: uuid.UUID, seq: int, mtype: MessageType, meta: dict, payload: bytes = b"") -> bytes:
    return encode_message(Message(mtype, sid, seq, time.time(), meta, payload))


def start(sid: uuid.UUID) -> bytes:
    return msg(sid, 1, MessageType.SESSION_START, {"structure": "test girder", "operator": "t"})


def frame(sid: uuid.UUID, seq: int) -> bytes:
    return msg(
        sid,
        seq,
        MessageType.FRAME,
        {"width": 640, "height": 480, "pose": {"x": 0.1 * seq, "y": 0, "yaw": 0}},
        JPEG + bytes([seq % 256]),
    )


def session_json(server: LiveServer, sid: uuid.UUID) -> dict:
    return httpx.get(f"{server.url}/api/sessions/{sid}").raise_for_status().json()


def make_ingest(settings):  # type: ignore[no-untyped-def]
    from server.link.ingest import Ingest
    from server.storage.db import make_engine, make_sessionmaker
    from server.storage.files import SessionFiles

    upgrade(settings.resolved_database_url())
    factory = make_sessionmaker(make_engine(settings.resolved_database_url()))
    return (
        factory,
        Ingest(factory, SessionFiles(settings.data_dir)),
        settings.resolved_database_url().removeprefix("sqlite:///"),
    )


def send_and_reply(ws, data: bytes):  # type: ignore[no-untyped-def]
    ws.send(data)
    return decode_message(ws.recv(timeout=10))


def end_message(sid: uuid.UUID, seq: int) -> bytes:
    return msg(sid, seq, MessageType.SESSION_END, {"reason": "done"})


def wait_job(url: str, job_id: int, timeout_s: float = 120) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = httpx.get(f"{url}/api/jobs/{job_id}").raise_for_status().json()
        if job["state"] in ("done", "failed", "cancelled"):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} did not finish")


def add_user(server: LiveServer, name: str, role: Role, password: str = "correct horse") -> None:
    engine = make_engine(server.settings.resolved_database_url())
    try:
        create_user(make_sessionmaker(engine), name, password, role)
    finally:
        engine.dispose()


def login(server: LiveServer, name: str, password: str = "correct horse") -> dict[str, str]:
    r = httpx.post(f"{server.url}/api/auth/token", data={"username": name, "password": password})
    assert r.status_code == 200, r.text
    return {"Authorization": f"Bearer {r.json()['access_token']}"}


def empty_session(live_server: LiveServer) -> uuid.UUID:
    """A session the robot started and sent nothing else to."""
    sid = uuid.uuid4()
    with connect(
        ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}
    ) as ws:
        ws.send(start(sid))
        decode_message(ws.recv(timeout=10))
    return sid


def steelscan(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "server.cli", *args], capture_output=True, text=True, timeout=timeout
    )


def assert_clean_error(proc: subprocess.CompletedProcess[str], fragment: str) -> None:
    assert proc.returncode != 0
    assert proc.stderr.strip().splitlines()[-1].startswith("error: ")
    assert fragment in proc.stderr
    assert "Traceback" not in proc.stderr
