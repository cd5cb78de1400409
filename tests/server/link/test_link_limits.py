"""What the link refuses for good and what it retries: non-finite numbers and values the
database refuses are permanent on both backends, and the station's message size limit,
stated in its handshake, is one the robot's own client obeys (real server and client)."""

import asyncio
import math
import uuid

import pytest

from robot_link.client import RobotLink
from robot_link.protocol import (
    MAX_BYTES_HEADER,
    Message,
    MessageType,
    ProtocolError,
    encode_message,
)
from server.config import Settings
from server.loopback import BackgroundServer, free_port
from tests.conftest import LiveServer, make_token
from tests.media import jpeg
from tests.server.helpers import (
    make_ingest,
    msg,
    robot_ws,
    send_and_reply,
    session_json,
    start,
)

NAN_META = [
    {"pose": {"x": math.nan, "y": 0.0, "yaw": 0.0}},
    {"battery_v": {"main": math.inf}},
    {"wheel_speed_mps": [0.0, -math.inf, 0.0, 0.0]},
]


def _raw(meta_json: bytes, sid: uuid.UUID, seq: int) -> bytes:
    """A TELEMETRY message whose meta is exactly ``meta_json`` (as a careless robot writes)."""
    good = msg(sid, seq, MessageType.TELEMETRY, {"note": "x"})
    header = bytearray(good[:44])
    header[40:44] = len(meta_json).to_bytes(4, "little")
    return bytes(header) + meta_json


def test_non_finite_numbers_are_refused_for_good_on_both_backends(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with robot_ws(live_server) as ws:
        send_and_reply(ws, start(sid))
        for seq, meta in enumerate(
            [
                b'{"pose":{"x":NaN,"y":0,"yaw":0}}',
                b'{"battery_v":{"main":Infinity}}',
                b'{"wheel_speed_mps":[0,-Infinity,0,0]}',
                b'{"ir_range_m":[1e999,0,0,0]}',
            ],
            start=2,
        ):
            reply = send_and_reply(ws, _raw(meta, sid, seq))
            assert reply.type is MessageType.ERROR and reply.seq == seq
            assert not reply.meta["retry"] and "non-finite" in reply.meta["error"], reply.meta
        ok = send_and_reply(ws, msg(sid, 9, MessageType.TELEMETRY, {"battery_v": {"main": 12.1}}))
        assert ok.meta["status"] == "stored"  # the link goes on
    assert session_json(live_server, sid)["telemetry"] == 1


@pytest.mark.parametrize("meta", NAN_META)
def test_the_client_never_sends_a_non_finite_number(meta: dict) -> None:
    with pytest.raises(ProtocolError, match="non-finite"):
        encode_message(Message(MessageType.TELEMETRY, uuid.uuid4(), 2, 1.0, meta))


def test_a_value_the_database_refuses_is_permanent_a_lost_connection_is_not(settings) -> None:  # type: ignore[no-untyped-def]
    from sqlalchemy.exc import DataError, OperationalError

    _, ingest, _ = make_ingest(settings)
    dbapi = ingest.engine.dialect.dbapi
    assert ingest.refuses_value(dbapi.DataError("invalid input syntax"))
    assert ingest.refuses_value(DataError("INSERT", {}, dbapi.DataError("out of range")))
    assert not ingest.refuses_value(dbapi.OperationalError("server closed the connection"))
    assert not ingest.refuses_value(OperationalError("INSERT", {}, Exception("gone")))
    assert not ingest.refuses_value(OSError(28, "No space left on device"))
    ingest.close()


def test_the_client_obeys_the_limit_the_station_states(tmp_path) -> None:  # type: ignore[no-untyped-def]
    limit = 2**20
    settings = Settings(
        data_dir=tmp_path / "data",
        database_url=f"sqlite:///{tmp_path / 'data' / 'steelscan.db'}",
        max_message_bytes=limit,
        auto_process=False,
    )
    token = make_token(settings)
    server = BackgroundServer(settings, free_port())
    server.start()
    small, big = jpeg(64, 48), jpeg(64, 48) + bytes(3 * limit)
    meta = {"width": 64, "height": 48}
    try:

        async def run() -> tuple[RobotLink, int]:
            link = RobotLink(server.url, token)
            await link.send(MessageType.SESSION_START, {"structure": "limits"})
            await link.send(MessageType.FRAME, meta, big)  # queued before the handshake
            await link.start()
            await link.flush(timeout_s=10)  # dropped, not sent again and again
            assert link.max_message_bytes == limit
            with pytest.raises(ProtocolError, match="limit"):  # known now: refused at once
                await link.send(MessageType.FRAME, meta, big)
            await link.send(MessageType.FRAME, meta, small)
            await link.flush(timeout_s=10)
            await link.close()
            return link, link.stats.sent

        link, sent = asyncio.run(run())
        assert link.stats.errors == 1 and link.stats.acked == 2 and sent == 2
        s = session_json(LiveServer(server.url, settings, token), link.session_id)
        assert s["frames"] == 1
    finally:
        server.stop()


def test_the_handshake_states_the_limit(live_server: LiveServer) -> None:
    with robot_ws(live_server) as ws:
        stated = ws.response.headers[MAX_BYTES_HEADER]
    assert int(stated) == live_server.settings.max_message_bytes
