"""Durable storage of robot messages: file first, then the database row, then the ACK."""

from __future__ import annotations

import threading
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Any, Literal

from sqlalchemy import Connection, bindparam, func, select
from sqlalchemy.exc import DataError, IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from robot_link.protocol import Message, MessageType
from server.errors import IngestError
from server.link.rows import (
    CLOUDS,
    FRAMES,
    RECEIVED,
    SESSIONS,
    TELEMETRY,
    RawInsert,
    data_row,
    end_session,
    start_session,
)
from server.storage.db import WalCheckpointer, is_sqlite
from server.storage.files import SessionFiles
from server.storage.models import (
    SessionStatus,
    utcnow,
)
from server.storage.space import DiskReserve

StoreStatus = Literal["stored", "duplicate"]


@dataclass(frozen=True)
class StoreResult:
    """What storing one message did."""

    status: StoreStatus
    session_ended: bool = False  # this message ended its session: process it
    late: bool = False  # stored into a session already ended: its results miss it
    superseded: tuple[str, ...] = ()  # sessions of the robot its SESSION_START ended


@dataclass
class _Owner:
    """What ingest needs to know of a stored session (cached: only ingest changes it)."""

    robot_id: int | None  # None: imported, not recorded by a robot
    end_seq: int | None  # the SESSION_END's seq once its robot ended it
    ended: bool = False  # ended, by its robot or by the station


class Ingest:
    """Stores each robot message exactly once per (session, seq).

    The hot path keeps one connection open and writes the rows of frames, clouds and
    telemetry with the DB-API's ``executemany`` (SQLAlchemy Core for the rare session rows):
    per group commit one INSERT per table and one commit (a duplicate query only after a
    resend). One transaction at a time.
    """

    def __init__(
        self,
        factory: sessionmaker[Session],
        files: SessionFiles,
        reserve: DiskReserve | None = None,
        max_live_per_robot: int = 4,
    ) -> None:
        self.factory = factory
        self.max_live_per_robot = max_live_per_robot
        self.engine = factory.kw["bind"]
        self.files = files
        self.reserve = reserve
        self._owners: dict[str, _Owner] = {}
        self._inserts = {
            table: RawInsert(table, self.engine.dialect)
            for table in (RECEIVED, FRAMES, CLOUDS, TELEMETRY)
        }
        self._dbapi_integrity_error: type[Exception] = self.engine.dialect.dbapi.IntegrityError
        self._dbapi_data_error: type[Exception] = self.engine.dialect.dbapi.DataError
        self._conn: Connection | None = None
        self._checkpointer: WalCheckpointer | None = None
        self._lock = threading.RLock()  # one transaction at a time on the one connection

    def store(self, message: Message, robot_id: int | None) -> StoreResult:
        """Store one decoded message durably; raise IngestError if it cannot be stored."""
        result = self.store_many([(message, robot_id)])[0]
        if isinstance(result, Exception):
            raise result
        return result

    def store_many(
        self, items: list[tuple[Message, int | None]], *, check: bool = False
    ) -> list[StoreResult | Exception]:
        """Store several messages in one transaction (group commit), in order; each gets its
        result, or the IngestError/OSError that refused it alone.

        Optimistic first: resends are rare, so the batch goes in without asking which of it
        is stored already; the primary key of ``received_messages`` refuses a duplicate, and
        then the batch is stored again with that check (``check``), message by message if
        the commit still fails. Any other failure of the transaction is isolated the same
        way: each message is stored alone, so one that cannot be stored fails only itself."""
        results: list[StoreResult | Exception] = []
        with self._lock:
            try:
                conn = self._connection()
                with conn.begin():
                    batch = _Batch(self._stored_already(conn, items) if check else set())
                    for message, robot_id in items:
                        try:
                            results.append(self._stage(conn, message, robot_id, batch))
                        except (IngestError, OSError) as exc:
                            results.append(exc)
                    # the hot rows as plain executemany: no statement compiling
                    for table, rows in batch.rows.items():
                        if rows:
                            self._inserts[table].execute(conn, rows)
            except (IntegrityError, self._dbapi_integrity_error):
                self._owners.clear()  # trust the database again
                if not check:
                    return self.store_many(items, check=True)
                if len(items) == 1:
                    return [StoreResult("duplicate")]
                return [self.store_many([item], check=True)[0] for item in items]
            except Exception as exc:
                self._owners.clear()
                self.close()  # a fresh connection next time
                if len(items) == 1:
                    return [exc]
                return [self.store_many([item])[0] for item in items]
            for sid, owner in batch.new_owners.items():
                self._owners[sid] = owner
            return results

    def refuses_value(self, exc: BaseException) -> bool:
        """Whether a failure to store is the database refusing a value of the message (a
        data error: out of range, not representable), which no resend can mend, as opposed
        to the station's own transient fault (a lost connection, a full disk)."""
        return isinstance(exc, (DataError, self._dbapi_data_error))

    def robot_of(self, sid: str) -> int | None:
        """The robot that recorded a session (None: unknown, or imported)."""
        owner = self._owners.get(sid)
        if owner is not None:
            return owner.robot_id
        with self.engine.connect() as conn:
            return conn.execute(select(SESSIONS.c.robot_id).where(SESSIONS.c.id == sid)).scalar()

    def close_quiet_sessions(self, idle_s: float) -> list[str]:
        """Close the files of every session without an append for ``idle_s`` seconds, and
        end the live sessions that got no message for that long (their robot never sent
        SESSION_END); the ids of the sessions ended. A robot that comes back later may still
        add to one: it was ended without a SESSION_END."""
        cutoff = utcnow() - timedelta(seconds=idle_s)
        last = (
            select(func.max(RECEIVED.c.received_at))
            .where(RECEIVED.c.session_id == SESSIONS.c.id)
            .scalar_subquery()
        )
        with self._lock:
            for sid in self.files.quiet_sessions(idle_s):
                self.files.close_session(sid)
            conn = self._connection()
            with conn.begin():
                quiet = list(
                    conn.execute(
                        select(SESSIONS.c.id).where(
                            SESSIONS.c.status == SessionStatus.live,
                            func.coalesce(last, SESSIONS.c.started_at) < cutoff,
                        )
                    ).scalars()
                )
                if quiet:
                    conn.execute(
                        SESSIONS.update()
                        .where(SESSIONS.c.id.in_(quiet))
                        .values(
                            status=SessionStatus.ended,
                            ended_at=utcnow(),
                            end_reason=f"no message for {idle_s:g} s: ended by the station",
                        )
                    )
            for sid in quiet:
                self.files.close_session(sid)
                self._owners.pop(sid, None)
        return quiet

    def _connection(self) -> Connection:
        """The connection ingest keeps open (checking one out of the pool per transaction
        costs as much as the inserts)."""
        if self._conn is None or self._conn.closed:
            self._conn = self.engine.connect()
            # the checkpointer's thread does them, not this one's commits
            if is_sqlite(self.engine):
                raw = self._conn.connection.driver_connection
                raw.execute("PRAGMA wal_autocheckpoint=0")
                # the log's file is cut back to this after a checkpoint
                raw.execute(f"PRAGMA journal_size_limit={WAL_SIZE_LIMIT}")
                if self._checkpointer is None:
                    self._checkpointer = WalCheckpointer(self.engine)
        return self._conn

    def close(self) -> None:
        """Drop the connection (not back to the pool: it has automatic checkpoints off)."""
        with self._lock:
            if self._conn is not None:
                self._conn.invalidate()
                self._conn.close()
                self._conn = None
            if self._checkpointer is not None:
                self._checkpointer.close()
                self._checkpointer = None

    @staticmethod
    def _stored_already(
        conn: Connection, items: list[tuple[Message, int | None]]
    ) -> set[tuple[str, int]]:
        """Which (session, seq) of a batch are stored: one primary-key range query per session
        (a row-value IN over both columns does not use the index in SQLite: 0.7 ms)."""
        by_session: dict[str, list[int]] = defaultdict(list)
        for m, _ in items:
            by_session[str(m.session_id)].append(m.seq)
        seen: set[tuple[str, int]] = set()
        for sid, seqs in by_session.items():
            rows = conn.execute(STORED, {"sid": sid, "seqs": seqs})
            seen.update((sid, r[0]) for r in rows)
        return seen

    def _owner(self, conn: Connection, sid: str, batch: _Batch) -> _Owner | None:
        owner = batch.new_owners.get(sid) or self._owners.get(sid)
        if owner is None:
            row = conn.execute(
                select(SESSIONS.c.robot_id, SESSIONS.c.status, SESSIONS.c.end_seq).where(
                    SESSIONS.c.id == sid
                )
            ).first()
            if row is not None:
                owner = _Owner(row[0], row[2], row[1] == SessionStatus.ended)
                self._owners[sid] = owner
        return owner

    def _stage(
        self, conn: Connection, message: Message, robot_id: int | None, batch: _Batch
    ) -> StoreResult:
        """Write one message's file and add its rows to the batch."""
        sid = str(message.session_id)
        owner = self._owner(conn, sid, batch)
        if message.type is MessageType.SESSION_START:
            if owner is not None:
                self._check_owner(sid, owner, robot_id)
                return StoreResult("duplicate")
        elif owner is None:
            raise IngestError(f"session {sid} is unknown: send SESSION_START first", retry=True)
        else:
            self._check_owner(sid, owner, robot_id)
            if self._check_not_after_end(sid, owner, message) == "duplicate":
                return StoreResult("duplicate")
        if (sid, message.seq) in batch.seen:
            return StoreResult("duplicate")
        if self.reserve is not None:
            self.reserve.claim(len(message.payload) + ROW_BYTES)
        superseded: tuple[str, ...] = ()
        if message.type is MessageType.SESSION_START and robot_id is not None:
            superseded = self._make_room(conn, robot_id, sid, batch)
        # the file first: a failed write adds no row
        self._add_rows(conn, message, sid, robot_id, batch)
        batch.seen.add((sid, message.seq))
        if superseded:
            return StoreResult("stored", superseded=superseded)
        was_ended = owner is not None and owner.ended
        if message.type is MessageType.SESSION_END and owner is not None:
            batch.new_owners[sid] = _Owner(owner.robot_id, message.seq, ended=True)
            # an END after the station ended the session: processed already, its data too
            return StoreResult("stored", session_ended=not was_ended, late=was_ended)
        return StoreResult("stored", late=was_ended)

    def _make_room(
        self, conn: Connection, robot_id: int, sid: str, batch: _Batch
    ) -> tuple[str, ...]:
        """End the robot's oldest live sessions beyond ``max_live_per_robot - 1`` (it is
        starting another: a robot that restarted without ending its last one), so that one
        robot can hold only so many sessions, and their files, open."""
        live = list(
            conn.execute(
                select(SESSIONS.c.id)
                .where(SESSIONS.c.robot_id == robot_id, SESSIONS.c.status == SessionStatus.live)
                .order_by(SESSIONS.c.started_at, SESSIONS.c.id)
            ).scalars()
        )
        over = live[: max(0, len(live) - self.max_live_per_robot + 1)]
        if not over:
            return ()
        conn.execute(
            SESSIONS.update()
            .where(SESSIONS.c.id.in_(over), SESSIONS.c.status == SessionStatus.live)
            .values(
                status=SessionStatus.ended,
                ended_at=utcnow(),
                end_reason=f"ended by the station: its robot started session {sid}",
            )
        )
        for old in over:
            self.files.close_session(old)
            batch.new_owners[old] = _Owner(robot_id, None, ended=True)
        return tuple(over)

    @staticmethod
    def _check_owner(sid: str, owner: _Owner, robot_id: int | None) -> None:
        if owner.robot_id is None and robot_id is not None:
            raise IngestError(f"session {sid} was imported, not recorded: robots cannot add to it")
        if owner.robot_id != robot_id:
            raise IngestError(f"session {sid} belongs to another robot")

    @staticmethod
    def _check_not_after_end(sid: str, owner: _Owner, message: Message) -> StoreStatus | None:
        """Messages sent before the SESSION_END (resends after a storage fault) are taken;
        nothing sent after it is, and a session ends once: its END again is a duplicate,
        another END is refused (an ended session never reopens)."""
        end = owner.end_seq
        if end is None:
            return None
        if message.type is MessageType.SESSION_END:
            if message.seq == end:
                return "duplicate"
            raise IngestError(
                f"session {sid} ended at seq {end}: a second SESSION_END (seq {message.seq}) "
                "is refused"
            )
        if message.seq > end:
            raise IngestError(
                f"session {sid} ended at seq {end}: {message.type.name} seq {message.seq} "
                "comes after its end"
            )
        return None

    def _add_rows(
        self, conn: Connection, message: Message, sid: str, robot_id: int | None, batch: _Batch
    ) -> None:
        """Write the message's payload (frames, clouds), then its rows: the session's at
        once (a start, an end), the rest into the batch."""
        rel, offset = None, None
        # the payload before the row: a failed write adds nothing
        if message.type in (MessageType.FRAME, MessageType.CLOUD):
            kind = "frames" if message.type is MessageType.FRAME else "clouds"
            rel, offset = self.files.append(sid, kind, message.payload)
        if message.type is MessageType.SESSION_END:  # before its row: a refused END adds none
            end_session(conn, sid, message.seq, message.meta.get("reason", "completed"))
            self.files.close_session(sid)
        if message.type is MessageType.SESSION_START:  # at once: the batch's rows refer to it
            start_session(conn, sid, robot_id, message.meta)
            batch.new_owners[sid] = _Owner(robot_id, None)
        batch.rows[RECEIVED].append(
            {
                "session_id": sid,
                "seq": message.seq,
                "type": message.type.name,
                "received_at": utcnow(),
            }
        )
        row = data_row(message, sid, rel, offset)
        if row is not None:
            batch.rows[row[0]].append(row[1])


STORED = select(RECEIVED.c.seq).where(
    RECEIVED.c.session_id == bindparam("sid"), RECEIVED.c.seq.in_(bindparam("seqs", expanding=True))
)


@dataclass
class _Batch:
    """What one group commit has gathered: rows per table, sessions started, keys stored."""

    seen: set[tuple[str, int]]
    new_owners: dict[str, _Owner] = field(default_factory=dict)
    rows: dict[Any, list[dict[str, Any]]] = field(default_factory=lambda: defaultdict(list))


ROW_BYTES = 4096  # what a message's rows may take on disk besides its payload (a page)
WAL_SIZE_LIMIT = 64 * 2**20  # bytes of write-ahead log kept on disk once checkpointed
