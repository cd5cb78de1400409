"""The robot's durable spool, alone and under the link client against the real server."""

import asyncio
import uuid
from pathlib import Path

import pytest

from robot_link.client import RobotLink
from robot_link.protocol import MessageType
from robot_link.spool import Spool, SpoolFull
from server.config import Settings
from server.loopback import BackgroundServer, free_port
from tests.conftest import LiveServer, make_token
from tests.server.helpers import JPEG, session_json


def test_spool_keeps_messages_on_disk_in_order_within_its_bound(tmp_path: Path) -> None:
    spool = Spool(tmp_path / "s", max_bytes=100, warn_fraction=0.8, fsync=False)
    spool.put(3, b"c" * 30)
    spool.put(1, b"a" * 30)
    assert spool.pending() == [1, 3] and spool.read(1) == b"a" * 30 and not spool.near_full
    spool.put(2, b"b" * 30)
    assert spool.near_full and spool.used_bytes == 90
    with pytest.raises(SpoolFull, match="90 of 100"):
        spool.put(4, b"d" * 30)
    spool.remove(1)
    (tmp_path / "s" / "000000000009.msg.tmp").write_bytes(b"half written")  # a crash mid-write
    sid = uuid.uuid4()
    spool.save_session(sid, 1024)
    again = Spool(tmp_path / "s", max_bytes=100)
    assert again.pending() == [2, 3] and again.load_session() == (sid, 1024)
    assert not list((tmp_path / "s").glob("*.tmp"))


def test_a_restarted_robot_resends_what_was_never_acknowledged(
    live_server: LiveServer, tmp_path: Path
) -> None:
    async def before_crash() -> uuid.UUID:
        link = RobotLink(
            live_server.url, live_server.token, spool=Spool(tmp_path / "spool", fsync=False)
        )
        # never connected: the messages only reach the spool before the computer "dies"
        await link.send(MessageType.SESSION_START, {"structure": "spooled"})
        for i in range(5):
            await link.send(MessageType.FRAME, {"width": 640, "height": 480}, JPEG + bytes([i]))
        return link.session_id

    async def after_restart() -> RobotLink:
        link = RobotLink(
            live_server.url, live_server.token, spool=Spool(tmp_path / "spool", fsync=False)
        )
        await link.start()
        await link.send(MessageType.FRAME, {"width": 640, "height": 480}, JPEG + b"new")
        await link.flush(timeout_s=30)
        await link.close()
        return link

    sid = asyncio.run(before_crash())
    link = asyncio.run(after_restart())
    assert link.session_id == sid  # the same session resumes
    # 5 from before the restart, 1 after, none twice
    assert session_json(live_server, sid)["frames"] == 6
    assert link.spool is not None and len(link.spool) == 0 and link.stats.spool_bytes == 0


def test_an_outage_longer_than_the_window_loses_nothing(tmp_path: Path, database_url: str) -> None:
    settings = Settings(
        database_url=database_url, data_dir=tmp_path / "data", job_workers=1, auto_process=False
    )
    token = make_token(settings)
    port = free_port()
    url = f"http://127.0.0.1:{port}"

    async def run() -> uuid.UUID:
        link = RobotLink(
            url, token, window=4, max_backoff_s=0.2, spool=Spool(tmp_path / "spool", fsync=False)
        )
        await link.start()  # the ground station is not up yet
        await link.send(MessageType.SESSION_START, {"structure": "long outage"})
        for i in range(40):  # ten times the window: a spooling link does not block on it
            await link.send(MessageType.FRAME, {"width": 640, "height": 480}, JPEG + bytes([i]))
        assert link.pending == 41
        server = BackgroundServer(settings, port)
        await asyncio.to_thread(server.start)
        try:
            await link.flush(timeout_s=60)
            await link.close()
        finally:
            await asyncio.to_thread(server.stop)
        return link.session_id

    sid = asyncio.run(run())
    server = BackgroundServer(settings, free_port())
    server.start()
    try:
        import httpx

        assert httpx.get(f"{server.url}/api/sessions/{sid}").json()["frames"] == 40
    finally:
        server.stop()
