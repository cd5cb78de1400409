"""One faulty message fails only itself: out-of-range fields are refused before the group
commit, a message the database refuses is isolated from the rest of its batch, and a
message over the size limit gets the protocol's ERROR instead of a dead link."""

from __future__ import annotations

import os
import threading
import time
import uuid
from pathlib import Path

import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from robot_link.protocol import (
    HEADER,
    MAGIC,
    PROTOCOL_VERSION,
    Message,
    MessageType,
    ProtocolError,
    decode_message,
    encode_message,
)
from server.errors import IngestError
from server.link.ingest import Ingest, StoreResult
from tests.conftest import LiveServer
from tests.media import jpeg
from tests.server.helpers import frame, make_ingest, msg, robot_ws, session_json, start


def _with_seq(data: bytes, seq: int) -> bytes:
    """A message re-headed with a seq the encoder would refuse."""
    fields = list(HEADER.unpack_from(data))
    fields[5] = seq
    return HEADER.pack(*fields) + data[HEADER.size :]


def test_seq_beyond_two_to_the_63_is_refused_by_both_ends() -> None:
    sid = uuid.uuid4()
    with pytest.raises(ProtocolError, match="2\\*\\*63"):
        encode_message(Message(MessageType.TELEMETRY, sid, 2**63, time.time(), {}))
    with pytest.raises(ProtocolError, match="2\\*\\*63"):
        decode_message(_with_seq(frame(sid, 2), 2**64 - 1))
    assert HEADER.unpack_from(frame(sid, 2))[:2] == (MAGIC, PROTOCOL_VERSION)


def test_a_robot_sending_huge_seqs_costs_another_robot_nothing(live_server: LiveServer) -> None:
    honest, attacker = uuid.uuid4(), uuid.uuid4()
    stop = threading.Event()
    errors: list[Message] = []

    def attack() -> None:
        with robot_ws(live_server) as ws:
            ws.send(start(attacker))
            ws.recv(timeout=10)
            seq = 2**63
            while not stop.is_set():
                ws.send(_with_seq(frame(attacker, 2), seq))
                errors.append(decode_message(ws.recv(timeout=10)))
                seq += 1

    thread = threading.Thread(target=attack)
    thread.start()
    try:
        with robot_ws(live_server) as ws:
            ws.send(start(honest))
            replies = [decode_message(ws.recv(timeout=10))]
            deadline = time.monotonic() + 10
            while not errors:  # the attack is under way before the honest frames go
                assert time.monotonic() < deadline, "the attacker got no answer"
                time.sleep(0.01)
            for seq in range(2, 82):
                ws.send(frame(honest, seq))
            replies += [decode_message(ws.recv(timeout=10)) for _ in range(80)]
    finally:
        stop.set()
        thread.join(timeout=30)
    assert all(r.type is MessageType.ACK and r.meta["status"] == "stored" for r in replies)
    assert session_json(live_server, honest)["frames"] == 80
    assert errors and all(e.type is MessageType.ERROR for e in errors)
    assert all(not e.meta["retry"] and "2**63" in e.meta["error"] for e in errors)


class _PoisonedIngest(Ingest):
    """Ingest whose database refuses one message's rows (as a constraint or a driver might)."""

    poison_seq = 13

    def _add_rows(self, conn, message, sid, robot_id, batch):  # type: ignore[no-untyped-def]
        if message.seq == self.poison_seq:
            raise RuntimeError("the database refused this row")
        return super()._add_rows(conn, message, sid, robot_id, batch)


def test_a_message_the_database_refuses_fails_only_itself(settings) -> None:  # type: ignore[no-untyped-def]
    factory, _, _ = make_ingest(settings)
    from server.storage.files import SessionFiles

    ingest = _PoisonedIngest(factory, SessionFiles(settings.data_dir))
    sid = uuid.uuid4()
    items = [(decode_message(start(sid)), None)]
    items += [(decode_message(frame(sid, seq)), None) for seq in range(2, 31)]
    results = ingest.store_many(items)
    failed = [i for i, r in enumerate(results) if not isinstance(r, StoreResult)]
    assert failed == [12] and isinstance(results[12], RuntimeError)
    assert all(r.status == "stored" for r in results if isinstance(r, StoreResult))
    again = ingest.store_many(items[1:3])  # the rest really is stored
    assert [r.status for r in again] == ["duplicate", "duplicate"]  # type: ignore[union-attr]
    ingest.close()


def test_an_oversize_message_gets_an_error_and_is_dropped_not_resent(
    live_server: LiveServer,
) -> None:
    sid = uuid.uuid4()
    limit = live_server.settings.max_message_bytes
    with robot_ws(live_server, max_size=None) as ws:
        ws.send(start(sid))
        decode_message(ws.recv(timeout=10))
        ws.send(frame(sid, 2)[:60] + b"\x00" * (limit + 4096))
        reply = decode_message(ws.recv(timeout=10))
        assert reply.type is MessageType.ERROR and reply.seq == 2
        assert not reply.meta["retry"] and "limit" in reply.meta["error"]
        ws.send(frame(sid, 3))  # the link goes on
        assert decode_message(ws.recv(timeout=10)).meta["status"] == "stored"
        # far over the limit the station closes before reading it (1009)
        with pytest.raises((ConnectionClosed, OSError)):
            ws.send(frame(sid, 4)[:60] + b"\x00" * (live_server.settings.ws_max_bytes + 1))
            ws.recv(timeout=10)
    assert session_json(live_server, sid)["frames"] == 1
    with pytest.raises(ProtocolError, match="limit"):  # and a robot never sends one
        encode_message(
            Message(
                MessageType.FRAME,
                sid,
                5,
                time.time(),
                {"width": 640, "height": 480},
                b"\xff\xd8" + bytes(limit),
            )
        )


def test_nothing_sent_after_a_session_end_is_stored_but_resends_from_before_are(
    settings,  # type: ignore[no-untyped-def]
) -> None:
    factory, ingest, _ = make_ingest(settings)
    sid = uuid.uuid4()
    end = msg(sid, 4, MessageType.SESSION_END, {"reason": "done"})
    results = ingest.store_many(
        [(decode_message(m), None) for m in (start(sid), frame(sid, 2), end, frame(sid, 5))]
    )
    assert [getattr(r, "status", None) for r in results[:3]] == ["stored"] * 3
    assert isinstance(results[3], IngestError) and "after its end" in str(results[3])
    assert not results[3].retry
    ingest.close()
    _, fresh, _ = make_ingest(settings)  # the end is known from the database too
    late = fresh.store_many([(decode_message(frame(sid, 3)), None)])  # sent before the end
    after = fresh.store_many([(decode_message(frame(sid, 6)), None)])
    assert getattr(late[0], "status", None) == "stored"
    assert isinstance(after[0], IngestError)
    fresh.close()


def test_robots_cannot_add_to_a_session_they_did_not_record(settings) -> None:  # type: ignore[no-untyped-def]
    from server.link.robots import create_robot
    from server.storage.models import InspectionSession

    factory, ingest, _ = make_ingest(settings)
    create_robot(factory, "first")
    create_robot(factory, "second")
    imported, theirs = uuid.uuid4(), uuid.uuid4()
    with factory() as db:
        db.add(InspectionSession(id=str(imported), structure="imported", robot_id=None))
        db.commit()
    assert ingest.store_many([(decode_message(start(theirs)), 1)])[0].status == "stored"  # type: ignore[union-attr]
    results = ingest.store_many(
        [(decode_message(frame(imported, 2)), 2), (decode_message(frame(theirs, 2)), 2)]
    )
    assert "imported" in str(results[0]) and "another robot" in str(results[1])
    ingest.close()


def test_a_robot_cannot_speak_on_another_robots_live_channel(live_server: LiveServer) -> None:
    """VIDEO and COMMAND_ACK reach the dashboards only from the robot that recorded the
    session."""
    import json

    from tests.conftest import make_token

    other_token = make_token(live_server.settings, "intruder")
    sid = uuid.uuid4()
    live_url = live_server.url.replace("http://", "ws://") + "/ws/live"

    def video(seq: int, marker: bytes) -> bytes:
        return msg(sid, seq, MessageType.VIDEO, {"width": 8, "height": 8}, jpeg(8, 8) + marker)

    fake_ack = msg(sid, 9, MessageType.COMMAND_ACK, {"cmd": "estop", "accepted": True})
    with (
        robot_ws(live_server) as owner,
        robot_ws(live_server, other_token) as intruder,
        connect(live_url) as browser,
    ):
        owner.send(start(sid))
        decode_message(owner.recv(timeout=10))
        intruder.send(video(1, b"FAKE"))
        intruder.send(fake_ack)
        time.sleep(0.5)
        owner.send(video(2, b"REAL"))
        owner.send(msg(sid, 3, MessageType.COMMAND_ACK, {"cmd": "stop", "accepted": True}))
        seen: list[bytes | str] = []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not any(
            isinstance(i, str) and '"command_ack"' in i for i in seen
        ):
            try:
                seen.append(browser.recv(timeout=1))
            except TimeoutError:
                continue
    videos = [i for i in seen if isinstance(i, bytes)]
    acks = [json.loads(i) for i in seen if isinstance(i, str) and '"command_ack"' in i]
    assert videos and all(v.endswith(b"REAL") for v in videos)
    assert [a["cmd"] for a in acks] == ["stop"]


def _open_files_of(sid: uuid.UUID) -> int:
    count = 0
    for fd in Path("/proc/self/fd").iterdir():
        try:
            count += str(sid) in os.readlink(fd)
        except OSError:
            continue
    return count


def test_a_session_its_robot_abandoned_is_ended_and_its_files_closed(
    tmp_path: Path, database_url: str
) -> None:
    """No SESSION_END and no message for the idle time: the station ends the session,
    closes its files, and still takes what the robot sends if it comes back."""
    from server.config import Settings
    from server.loopback import BackgroundServer, free_port
    from tests.conftest import make_token

    settings = Settings(
        data_dir=tmp_path / "data",
        database_url=database_url,
        job_workers=1,
        auto_process=False,
        session_idle_s=0.8,
    )
    token = make_token(settings)
    server = BackgroundServer(settings, free_port())
    server.start()
    live = LiveServer(server.url, settings, token)
    sid = uuid.uuid4()
    try:
        with robot_ws(live) as ws:
            ws.send(start(sid))
            ws.send(frame(sid, 2))
            assert [decode_message(ws.recv(timeout=10)).type for _ in range(2)] == [
                MessageType.ACK
            ] * 2
        assert _open_files_of(sid) > 0
        deadline = time.monotonic() + 15
        while session_json(live, sid)["status"] != "ended" and time.monotonic() < deadline:
            time.sleep(0.2)
        session = session_json(live, sid)
        assert session["status"] == "ended" and "no message" in session["end_reason"]
        assert _open_files_of(sid) == 0
        with robot_ws(live) as ws:  # the robot is back
            ws.send(frame(sid, 3))
            assert decode_message(ws.recv(timeout=10)).meta["status"] == "stored"
        assert session_json(live, sid)["frames"] == 2
    finally:
        server.stop()


def test_slow_or_many_connections_from_one_address_cannot_keep_a_robot_out(
    tmp_path: Path, database_url: str
) -> None:
    """Sockets from one address sending a partial request head are capped per address and
    closed at the head deadline; a robot from another address connects all along."""
    import socket

    from server.config import Settings
    from server.loopback import BackgroundServer, free_port
    from tests.conftest import make_token

    settings = Settings(
        data_dir=tmp_path / "data",
        database_url=database_url,
        job_workers=1,
        max_connections_per_client=20,
        request_head_timeout_s=1.0,
    )
    token = make_token(settings)
    port = free_port()
    server = BackgroundServer(settings, port)
    server.start()
    live = LiveServer(server.url, settings, token)
    slow: list[socket.socket] = []
    try:
        for _ in range(60):
            s = socket.socket()
            s.bind(("127.0.0.2", 0))  # the attacker's address
            s.settimeout(5)
            s.connect(("127.0.0.1", port))
            s.sendall(b"GET /api/health HTTP/1.1\r\nHost: x\r\nX-Slow: ")
            slow.append(s)
        time.sleep(0.3)

        def closed(s: socket.socket) -> bool:
            s.settimeout(0.01)
            try:
                return s.recv(1) == b""
            except TimeoutError:
                return False
            except OSError:
                return True

        assert sum(closed(s) for s in slow) >= 40  # over the cap: refused at once
        sid = uuid.uuid4()
        with robot_ws(live) as ws:
            ws.send(start(sid))
            assert decode_message(ws.recv(timeout=10)).meta["status"] == "stored"
        time.sleep(1.5)
        assert all(closed(s) for s in slow)  # the rest at the head deadline
    finally:
        for s in slow:
            s.close()
        server.stop()


def test_a_robot_sending_garbage_is_cut_off_and_barred_others_are_not(
    live_server: LiveServer,
) -> None:
    from websockets.exceptions import InvalidStatus

    from tests.conftest import make_token

    garbage = b"STLS" + bytes(60)
    bad_token = make_token(live_server.settings, "babbler")
    with robot_ws(live_server, bad_token) as ws:
        with pytest.raises(ConnectionClosed):
            for _ in range(500):
                ws.send(garbage)
            while True:
                ws.recv(timeout=10)
        assert ws.close_code == 1008
    with pytest.raises(InvalidStatus):  # barred: refused before the upgrade
        with robot_ws(live_server, bad_token):
            pass
    sid = uuid.uuid4()
    with robot_ws(live_server) as ws:
        ws.send(start(sid))
        assert decode_message(ws.recv(timeout=10)).meta["status"] == "stored"
