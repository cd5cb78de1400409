"""One faulty message fails only itself: out-of-range fields are refused before the group
commit, a message the database refuses is isolated from the rest of its batch, and a
message over the size limit gets the protocol's ERROR instead of a dead link."""

from __future__ import annotations

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
from server.link.ingest import Ingest, StoreResult
from tests.conftest import LiveServer
from tests.server.test_ingest import _ingest, frame, session_json, start, ws_url


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
    headers = {"Authorization": f"Bearer {live_server.token}"}
    honest, attacker = uuid.uuid4(), uuid.uuid4()
    stop = threading.Event()
    errors: list[Message] = []

    def attack() -> None:
        with connect(ws_url(live_server), additional_headers=headers) as ws:
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
        with connect(ws_url(live_server), additional_headers=headers) as ws:
            ws.send(start(honest))
            replies = [decode_message(ws.recv(timeout=10))]
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


def test_a_message_the_database_refuses_fails_only_itself(tmp_path: Path) -> None:
    factory, _, _ = _ingest(tmp_path)
    from server.storage.files import SessionFiles

    ingest = _PoisonedIngest(factory, SessionFiles(tmp_path / "data"))
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
    with connect(
        ws_url(live_server),
        additional_headers={"Authorization": f"Bearer {live_server.token}"},
        max_size=None,
    ) as ws:
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
