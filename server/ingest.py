"""Durable storage of robot messages: file first, then the database row, then the ACK."""

from __future__ import annotations

import asyncio
import queue
import threading
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any, Literal

from sqlalchemy import insert, select, tuple_
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from robot_link.protocol import Message, MessageType
from server.errors import IngestError
from server.models import (
    Cloud,
    Frame,
    InspectionSession,
    ReceivedMessage,
    SessionStatus,
    TelemetrySample,
    utcnow,
)
from server.storage import SessionFiles

StoreStatus = Literal["stored", "duplicate"]


@dataclass(frozen=True)
class StoreResult:
    """What storing one message did."""

    status: StoreStatus
    session_ended: bool = False


class Ingest:
    """Stores each robot message exactly once per (session, seq)."""

    def __init__(self, factory: sessionmaker[Session], files: SessionFiles) -> None:
        self.factory = factory
        self.files = files

    def store(self, message: Message, robot_id: int | None) -> StoreResult:
        """Store one decoded message durably; raise IngestError if it cannot be stored."""
        result = self.store_many([(message, robot_id)])[0]
        if isinstance(result, Exception):
            raise result
        return result

    def store_many(self, items: list[tuple[Message, int | None]]) -> list[StoreResult | Exception]:
        """Store several messages in one transaction (group commit), in order; each gets its
        result, or the IngestError/OSError that refused it alone. Rows go in as one
        multi-row INSERT per table. Should the commit fail as a whole, each message is
        stored again on its own."""
        with self.factory() as db:
            results: list[StoreResult | Exception] = []
            # what of this batch is stored already: one query, not one per message
            keys = [(str(m.session_id), m.seq) for m, _ in items]
            seen: set[tuple[str, int]] = {
                (row.session_id, row.seq)
                for row in db.execute(select(ReceivedMessage.session_id, ReceivedMessage.seq).where(tuple_(ReceivedMessage.session_id, ReceivedMessage.seq).in_(keys)))
            } if keys else set()
            batch = _Batch(seen)
            for message, robot_id in items:
                try:
                    results.append(self._stage(db, message, robot_id, batch))
                except (IngestError, OSError) as exc:
                    results.append(exc)
            try:
                for model, rows in batch.rows.items():
                    if rows:
                        db.execute(insert(model), rows)
                db.commit()
            except IntegrityError:
                db.rollback()
                if len(items) == 1:
                    return [StoreResult("duplicate")]
                return [self.store_many([item])[0] for item in items]
        return results

    def _stage(self, db: Session, message: Message, robot_id: int | None, batch: _Batch) -> StoreResult:
        """Write one message's file and add its rows to the batch."""
        sid = str(message.session_id)
        if sid not in batch.sessions:
            batch.sessions[sid] = db.get(InspectionSession, sid)
        session = batch.sessions[sid]
        if message.type is MessageType.SESSION_START:
            if session is not None:
                self._check_owner(session, robot_id)
                return StoreResult("duplicate")
        elif session is None:
            raise IngestError(f"session {sid} is unknown: send SESSION_START first", retry=True)
        else:
            self._check_owner(session, robot_id)
        if (sid, message.seq) in batch.seen:
            return StoreResult("duplicate")
        ended = self._add_rows(db, message, sid, robot_id, session, batch)  # the file first: a failed write adds no row
        batch.seen.add((sid, message.seq))
        return StoreResult("stored", session_ended=ended)

    @staticmethod
    def _check_owner(session: InspectionSession, robot_id: int | None) -> None:
        if session.robot_id is not None and robot_id is not None and session.robot_id != robot_id:
            raise IngestError(f"session {session.id} belongs to another robot")

    def _add_rows(self, db: Session, message: Message, sid: str, robot_id: int | None, session: InspectionSession | None,
                  batch: _Batch) -> bool:
        meta = message.meta
        pose = meta.get("pose") or {}
        mtype = message.type
        rel = None
        if mtype is MessageType.FRAME:  # files before rows: a write that fails adds nothing
            rel = self.files.frame_relpath(sid, message.seq)
        elif mtype is MessageType.CLOUD:
            rel = self.files.cloud_relpath(sid, message.seq, meta["encoding"])
        if rel is not None:
            # no temporary name: the row that makes the file visible is committed after it,
            # and a resend after a crash writes it again
            self.files.write_in_place(rel, message.payload)
        if mtype is MessageType.SESSION_START:
            session = InspectionSession(id=sid, robot_id=robot_id, structure=meta["structure"], operator=meta.get("operator", ""),
                                        location=meta.get("location", ""), calibration=meta.get("calibration", {}))
            db.add(session)
            db.flush()
            batch.sessions[sid] = session
        batch.rows[ReceivedMessage].append({"session_id": sid, "seq": message.seq, "type": mtype.name, "received_at": utcnow()})
        poses = {"pose_x": pose.get("x"), "pose_y": pose.get("y"), "pose_yaw": pose.get("yaw")}
        if mtype is MessageType.FRAME:
            batch.rows[Frame].append({"session_id": sid, "seq": message.seq, "timestamp": message.timestamp, "width": meta["width"],
                                      "height": meta["height"], "path": rel, "size_bytes": len(message.payload), **poses})
        elif mtype is MessageType.CLOUD:
            intrinsics = {k: meta[k] for k in ("fx", "fy", "cx", "cy") if k in meta}
            batch.rows[Cloud].append({"session_id": sid, "seq": message.seq, "timestamp": message.timestamp,
                                      "encoding": meta["encoding"], "width": meta["width"], "height": meta["height"],
                                      "intrinsics": intrinsics, "path": rel, "size_bytes": len(message.payload), **poses})
        elif mtype is MessageType.TELEMETRY:
            batch.rows[TelemetrySample].append({"session_id": sid, "seq": message.seq, "timestamp": message.timestamp, "data": meta})
        elif mtype is MessageType.SESSION_END:
            assert session is not None
            session.status = SessionStatus.ended
            session.ended_at = utcnow()
            session.end_reason = meta.get("reason", "completed")
            return True
        return False


@dataclass
class _Batch:
    """What one group commit has gathered: rows per table, sessions looked up, keys stored."""

    seen: set[tuple[str, int]]
    sessions: dict[str, InspectionSession | None] = field(default_factory=dict)
    rows: dict[Any, list[dict[str, Any]]] = field(default_factory=lambda: defaultdict(list))


class GroupCommit:
    """Stores the messages of every robot connection on one writer thread, as many per
    transaction as have arrived meanwhile (up to ``max_batch``): one SQLite commit for many
    frames, each acknowledged only once its transaction is committed."""

    def __init__(self, ingest: Ingest, max_batch: int = 128) -> None:
        self.ingest = ingest
        self.max_batch = max_batch
        self._queue: queue.SimpleQueue[tuple[Message, int | None, asyncio.Future[StoreResult], asyncio.AbstractEventLoop] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="ingest-writer", daemon=True)
        self._thread.start()

    def store(self, message: Message, robot_id: int | None) -> asyncio.Future[StoreResult]:
        """Queue one message; the future resolves when it is durably stored (or refused)."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[StoreResult] = loop.create_future()
        self._queue.put((message, robot_id, future, loop))
        return future

    def close(self) -> None:
        """Store what is queued, then stop the writer."""
        self._queue.put(None)
        self._thread.join(timeout=30)

    def _run(self) -> None:
        while True:
            first = self._queue.get()
            if first is None:
                return
            batch = [first]
            while len(batch) < self.max_batch:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is None:
                    self._queue.put(None)
                    break
                batch.append(item)
            try:
                results: list[StoreResult | Exception] = self.ingest.store_many([(m, r) for m, r, _, _ in batch])
            except Exception as exc:  # the database itself failed: every message of the batch hears it  # noqa: BLE001
                results = [exc] * len(batch)
            for (_, _, future, loop), result in zip(batch, results):
                loop.call_soon_threadsafe(_settle, future, result)


def _settle(future: asyncio.Future[StoreResult], result: StoreResult | Exception) -> None:
    if future.done():
        return
    if isinstance(result, Exception):
        future.set_exception(result)
    else:
        future.set_result(result)
