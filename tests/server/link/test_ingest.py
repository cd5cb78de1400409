"""The robot websocket against the real uvicorn server, data directory and database (each
test that takes ``settings`` runs on SQLite and on PostgreSQL)."""

import asyncio
import time
import uuid

import httpx
import numpy as np
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from robot_link.client import RobotLink
from robot_link.clouds import encode_depth_png
from robot_link.protocol import MessageType, decode_message
from tests.conftest import LiveServer
from tests.server.helpers import (
    JPEG,
    frame,
    make_ingest,
    msg,
    robot_ws,
    session_json,
    start,
    ws_url,
)


def test_robot_link_stores_everything_once_and_acks(live_server: LiveServer) -> None:
    async def run() -> uuid.UUID:
        link = RobotLink(live_server.url, live_server.token)
        await link.start()
        await link.send(MessageType.SESSION_START, {"structure": "test girder"})
        for i in range(5):
            await link.send(MessageType.FRAME, {"width": 640, "height": 480}, JPEG + bytes([i]))
        depth = np.full((4, 6), 1.5, np.float32)
        await link.send(
            MessageType.CLOUD,
            {
                "encoding": "png16_depth_mm",
                "width": 6,
                "height": 4,
                "fx": 5.0,
                "fy": 5.0,
                "cx": 2.5,
                "cy": 1.5,
            },
            encode_depth_png(depth),
        )
        await link.send(MessageType.TELEMETRY, {"battery_v": {"main": 12.2}})
        await link.flush(timeout_s=20)
        assert link.stats.acked == 8 and link.pending == 0
        await link.close()
        return link.session_id

    sid = asyncio.run(run())
    s = session_json(live_server, sid)
    assert (s["frames"], s["clouds"], s["telemetry"], s["status"]) == (5, 1, 1, "live")
    img = httpx.get(f"{live_server.url}/api/sessions/{sid}/frames/3/image")
    assert img.status_code == 200 and img.content == JPEG + bytes([1])


def test_resent_messages_are_acknowledged_but_stored_once(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with robot_ws(live_server) as ws:
        statuses = []
        for data in [
            start(sid),
            frame(sid, 2),
            frame(sid, 3),
            start(sid),
            frame(sid, 2),
            frame(sid, 3),
        ]:
            ws.send(data)
            reply = decode_message(ws.recv(timeout=10))
            assert reply.type is MessageType.ACK
            statuses.append(reply.meta["status"])
    assert statuses == ["stored"] * 3 + ["duplicate"] * 3
    assert session_json(live_server, sid)["frames"] == 2


def test_malformed_messages_get_errors_and_lose_nothing(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with connect(
        ws_url(live_server),
        additional_headers={"Authorization": f"Bearer {live_server.token}"},
        max_size=None,
    ) as ws:
        ws.send(start(sid))
        ws.send(frame(sid, 2))
        assert [decode_message(ws.recv(timeout=10)).meta["status"] for _ in range(2)] == [
            "stored",
            "stored",
        ]
        bad = [
            b"garbage",
            frame(sid, 3)[:-300].replace(b"\xff\xd8", b"\x00\x00", 1),
            b"STLS" + b"\x09" * 60,
        ]
        for data in bad:
            ws.send(data)
            reply = decode_message(ws.recv(timeout=10))
            assert reply.type is MessageType.ERROR and "malformed" in reply.meta["error"]
        ws.send("a text message")
        assert decode_message(ws.recv(timeout=10)).type is MessageType.ERROR
        ws.send(frame(uuid.uuid4(), 5))  # a session nobody started
        reply = decode_message(ws.recv(timeout=10))
        assert reply.type is MessageType.ERROR and "unknown" in reply.meta["error"]
        ws.send(frame(sid, 4))  # the connection still works
        assert decode_message(ws.recv(timeout=10)).meta["status"] == "stored"
    assert session_json(live_server, sid)["frames"] == 2


@pytest.mark.parametrize("token", ["wrong-token", ""])
def test_wrong_token_is_refused(live_server: LiveServer, token: str) -> None:
    with pytest.raises(InvalidStatus) as info:
        with connect(ws_url(live_server), additional_headers={"Authorization": f"Bearer {token}"}):
            pass
    assert info.value.response.status_code == 403


def test_rest_errors_are_json_with_the_right_status(live_server: LiveServer) -> None:
    r = httpx.get(f"{live_server.url}/api/sessions/nope")
    assert r.status_code == 404 and "not found" in r.json()["detail"]
    assert httpx.get(f"{live_server.url}/api/jobs/999").status_code == 404
    assert (
        httpx.get(f"{live_server.url}/openapi.json").json()["info"]["title"]
        == "steelscan ground station"
    )


def test_link_reconnects_and_resends_without_duplicates(live_server: LiveServer) -> None:
    async def run() -> tuple[uuid.UUID, RobotLink]:
        link = RobotLink(live_server.url, live_server.token, window=8)
        await link.start()
        await link.send(MessageType.SESSION_START, {"structure": "flaky link"})
        for i in range(30):
            if i in (10, 20) and link._ws is not None:
                link._ws.transport.abort()  # the network drops, no close handshake
            await link.send(MessageType.FRAME, {"width": 640, "height": 480}, JPEG + bytes([i]))
        await link.flush(timeout_s=30)
        await link.close()
        return link.session_id, link

    sid, link = asyncio.run(run())
    assert link.stats.reconnects >= 1
    assert session_json(live_server, sid)["frames"] == 30


def test_browser_command_reaches_the_robot_and_frames_reach_the_browser(
    live_server: LiveServer,
) -> None:
    import json as _json

    sid = uuid.uuid4()
    live_url = live_server.url.replace("http://", "ws://") + "/ws/live"
    with (
        robot_ws(live_server) as robot,
        connect(live_url) as browser,
    ):
        robot.send(start(sid))
        decode_message(robot.recv(timeout=10))
        robot.send(frame(sid, 2))
        decode_message(robot.recv(timeout=10))
        got_frame = False
        for _ in range(10):  # events and the frame, in whatever order
            item = browser.recv(timeout=10)
            if isinstance(item, bytes):
                head_len = int.from_bytes(item[:4], "little")
                header = _json.loads(item[4 : 4 + head_len])
                assert header["session_id"] == str(sid) and item[4 + head_len :].startswith(
                    b"\xff\xd8"
                )
                got_frame = True
                break
        assert got_frame
        browser.send(_json.dumps({"session_id": str(sid), "cmd": "estop"}))
        command = decode_message(robot.recv(timeout=10))
        assert command.type is MessageType.COMMAND and command.meta["cmd"] == "estop"
        browser.send(_json.dumps({"session_id": str(uuid.uuid4()), "cmd": "stop"}))
        browser.send("not json")
        replies = []
        while len([r for r in replies if r.get("type") == "command_result"]) < 3:
            item = browser.recv(timeout=10)
            if isinstance(item, str):
                replies.append(_json.loads(item))
        results = [r for r in replies if r.get("type") == "command_result"]
        assert results[0]["ok"] is True and results[0]["seq"] == command.seq
        assert "no robot" in results[1]["error"] and "bad command" in results[2]["error"]


def test_api_docs_need_no_internet(live_server: LiveServer) -> None:
    import re

    page = httpx.get(f"{live_server.url}/docs").text
    assets = re.findall(r'(?:src|href)="([^"]+)"', page) + re.findall(r"url: ?'([^']+)'", page)
    assert assets and all(a.startswith("/") for a in assets), assets
    for a in assets:
        assert httpx.get(live_server.url + a).status_code == 200, a


def test_a_robot_over_its_rate_limit_is_slowed_not_lost(settings) -> None:  # type: ignore[no-untyped-def]
    from server.loopback import BackgroundServer, free_port
    from tests.conftest import make_token

    settings = settings.model_copy(update={"robot_messages_per_s": 100, "robot_message_burst": 10})
    token = make_token(settings)
    server = BackgroundServer(settings, free_port())
    server.start()
    try:

        async def run() -> RobotLink:
            link = RobotLink(server.url, token, window=64, max_backoff_s=0.5)
            await link.start()
            await link.send(MessageType.SESSION_START, {"structure": "chatty robot"})
            for i in range(60):
                await link.send(MessageType.FRAME, {"width": 640, "height": 480}, JPEG + bytes([i]))
            await link.flush(timeout_s=30)
            await link.close()
            return link

        link = asyncio.run(run())
        assert link.stats.errors > 0  # it was told to slow down...
        frames = httpx.get(f"{server.url}/api/sessions/{link.session_id}").json()["frames"]
        assert frames == 60  # ...and lost nothing
    finally:
        server.stop()


def test_group_commit_stores_a_lone_message_at_once_and_batches_under_load(settings) -> None:  # type: ignore[no-untyped-def]
    """A quiet station stores a message on the caller's thread (acknowledged without a
    hand-off); a burst goes to the writer's group commits; every message is stored once."""
    from server.link.group_commit import QUIET_S, GroupCommit
    from server.link.ingest import Ingest
    from server.link.robots import create_robot
    from server.storage.db import make_engine, make_sessionmaker, upgrade
    from server.storage.files import SessionFiles

    upgrade(settings.resolved_database_url())
    factory = make_sessionmaker(make_engine(settings.resolved_database_url()))
    create_robot(factory, "r")
    writer = GroupCommit(Ingest(factory, SessionFiles(settings.data_dir)))
    sid = uuid.uuid4()

    async def run() -> tuple[bool, int, list[str]]:
        first = writer.store(decode_message(start(sid)), 1)
        at_once = first.done()
        await first
        time.sleep(2 * QUIET_S)
        burst = [writer.store(decode_message(frame(sid, seq)), 1) for seq in range(2, 42)]
        queued = sum(not f.done() for f in burst)
        return at_once, queued, [r.status for r in await asyncio.gather(*burst)]

    try:
        at_once, queued, statuses = asyncio.run(run())
    finally:
        writer.close()
    assert at_once
    assert queued >= 38  # after the first, the burst joins group commits
    assert statuses == ["stored"] * 40
    from sqlalchemy import func, select

    from server.storage.models import Frame

    with factory() as db:
        assert (
            db.scalar(select(func.count()).select_from(Frame).where(Frame.session_id == str(sid)))
            == 40
        )


def test_rows_stored_by_the_fast_path_read_back_as_the_orm_writes_them(settings) -> None:  # type: ignore[no-untyped-def]
    from sqlalchemy import select

    from server.storage.models import Cloud, Frame, ReceivedMessage, TelemetrySample

    factory, ingest, _ = make_ingest(settings)
    sid = uuid.uuid4()
    intrinsics = {"fx": 195.0, "fy": 196.5, "cx": 111.5, "cy": 85.5}
    try:
        for raw in (
            start(sid),
            frame(sid, 2),
            msg(
                sid,
                3,
                MessageType.CLOUD,
                {
                    "encoding": "png16_depth_mm",
                    "width": 6,
                    "height": 4,
                    **intrinsics,
                    "pose": {"x": 1.25, "y": -0.5, "yaw": 0.1},
                },
                encode_depth_png(np.full((4, 6), 1.5, np.float32)),
            ),
            msg(
                sid,
                4,
                MessageType.TELEMETRY,
                {"battery_v": {"main": 12.2}, "ir_edge": [True, False, False, True]},
            ),
        ):
            assert ingest.store(decode_message(raw), None).status == "stored"
        # the primary key still catches resends
        assert ingest.store(decode_message(frame(sid, 2)), None).status == "duplicate"
    finally:
        ingest.close()
    with factory() as db:
        f = db.scalars(select(Frame).where(Frame.session_id == str(sid))).one()
        c = db.scalars(select(Cloud).where(Cloud.session_id == str(sid))).one()
        t = db.scalars(select(TelemetrySample).where(TelemetrySample.session_id == str(sid))).one()
        received = db.scalars(
            select(ReceivedMessage)
            .where(ReceivedMessage.session_id == str(sid))
            .order_by(ReceivedMessage.seq)
        ).all()
    assert (f.seq, f.width, f.height, f.pose_x, f.size_bytes) == (
        2,
        640,
        480,
        pytest.approx(0.2),
        len(JPEG) + 1,
    )
    assert c.intrinsics == intrinsics and (c.encoding, c.pose_x, c.pose_y) == (
        "png16_depth_mm",
        1.25,
        -0.5,
    )
    assert t.data["battery_v"] == {"main": 12.2} and t.data["ir_edge"] == [True, False, False, True]
    assert [r.type for r in received] == ["SESSION_START", "FRAME", "CLOUD", "TELEMETRY"]
    # datetimes, not strings
    assert all(
        abs((r.received_at - received[0].received_at).total_seconds()) < 60 for r in received
    )


def test_the_write_ahead_log_is_checkpointed_off_the_ingest_path(tmp_path) -> None:  # type: ignore[no-untyped-def]
    import sqlite3

    from server.config import Settings

    factory, ingest, db_path = make_ingest(Settings(data_dir=tmp_path / "data"))
    sid = uuid.uuid4()

    def frames_in_main_file() -> int:
        # ``immutable`` reads the database file alone, not its write-ahead log: rows appear
        # there only once a checkpoint has copied them
        main = sqlite3.connect(f"file:{db_path}?immutable=1", uri=True)
        try:
            return int(main.execute("SELECT count(*) FROM frames").fetchone()[0])
        finally:
            main.close()

    try:
        ingest.store(decode_message(start(sid)), None)
        for seq in range(2, 52):
            ingest.store(decode_message(frame(sid, seq)), None)
        conn = ingest._connection()
        # not in its commits
        assert (
            conn.connection.driver_connection.execute("PRAGMA wal_autocheckpoint").fetchone()[0]
            == 0
        )
        deadline = time.monotonic() + 10
        while frames_in_main_file() < 50 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert frames_in_main_file() == 50  # ... but by the checkpointer's thread
    finally:
        ingest.close()
    with factory.kw["bind"].connect() as other:  # the pool never hands out ingest's connection
        assert (
            other.connection.driver_connection.execute("PRAGMA wal_autocheckpoint").fetchone()[0]
            == 1000
        )
