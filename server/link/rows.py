"""The rows a robot message becomes: its session's (started, ended once), and its frame,
cloud or telemetry row; and the raw INSERT that writes a group commit's rows."""

from __future__ import annotations

from typing import Any

from sqlalchemy import Connection, func

from robot_link.protocol import Message, MessageType
from server.errors import IngestError
from server.storage.models import (
    Cloud,
    Frame,
    InspectionSession,
    ReceivedMessage,
    SessionStatus,
    TelemetrySample,
    utcnow,
)

SESSIONS = InspectionSession.__table__
RECEIVED = ReceivedMessage.__table__
FRAMES = Frame.__table__
CLOUDS = Cloud.__table__
TELEMETRY = TelemetrySample.__table__


def start_session(conn: Connection, sid: str, robot_id: int | None, meta: dict[str, Any]) -> None:
    """The session's row, from its SESSION_START's meta."""
    conn.execute(
        SESSIONS.insert().values(
            id=sid,
            robot_id=robot_id,
            structure=meta["structure"],
            operator=meta.get("operator", ""),
            location=meta.get("location", ""),
            calibration=meta.get("calibration", {}),
        )
    )


def end_session(conn: Connection, sid: str, seq: int, reason: str) -> None:
    """End the session at its SESSION_END ``seq``, once: only where no END is recorded (and
    the database's trigger refuses to reopen an ended session or move its end)."""
    ended = conn.execute(
        SESSIONS.update()
        .where(SESSIONS.c.id == sid, SESSIONS.c.end_seq.is_(None))
        .values(
            status=SessionStatus.ended,
            end_seq=seq,
            ended_at=func.coalesce(SESSIONS.c.ended_at, utcnow()),
            end_reason=reason,
        )
    )
    if ended.rowcount != 1:
        raise IngestError(f"session {sid} has ended already: SESSION_END refused")


def data_row(
    message: Message, sid: str, path: str | None, offset: int | None
) -> tuple[Any, dict[str, Any]] | None:
    """The table and values of a FRAME's, CLOUD's or TELEMETRY's row (``path``, ``offset``:
    where its payload was written); None for other messages."""
    meta, mtype = message.meta, message.type
    pose = meta.get("pose") or {}
    poses = {"pose_x": pose.get("x"), "pose_y": pose.get("y"), "pose_yaw": pose.get("yaw")}
    common = {"session_id": sid, "seq": message.seq, "timestamp": message.timestamp}
    if mtype is MessageType.TELEMETRY:
        return TELEMETRY, {**common, "data": meta}
    if mtype not in (MessageType.FRAME, MessageType.CLOUD):
        return None
    stored = {"path": path, "data_offset": offset, "size_bytes": len(message.payload), **poses}
    size = {"width": meta["width"], "height": meta["height"]}
    if mtype is MessageType.FRAME:
        return FRAMES, {**common, **size, **stored}
    intrinsics = {k: meta[k] for k in ("fx", "fy", "cx", "cy") if k in meta}
    return CLOUDS, {
        **common,
        **size,
        **stored,
        "encoding": meta["encoding"],
        "intrinsics": intrinsics,
    }


class RawInsert:
    """A table's INSERT of every column but the autoincrement key, for the DB-API's
    ``executemany``: the values converted by each column's own SQLAlchemy type (JSON,
    datetimes), so rows read back exactly as the ORM writes them, without compiling a
    statement per transaction (~75 µs each: a third of storing a frame)."""

    def __init__(self, table: Any, dialect: Any) -> None:
        self.table = table
        columns = [c.name for c in table.columns if c is not table.autoincrement_column]
        marks = {"qmark": "?", "format": "%s", "pyformat": "%s"}.get(dialect.paramstyle)
        self.sql = (
            None
            if marks is None
            else f"INSERT INTO {table.name} ({', '.join(columns)}) VALUES ({', '.join([marks] * len(columns))})"
        )
        self._convert = [
            (name, table.c[name].type.dialect_impl(dialect).bind_processor(dialect))
            for name in columns
        ]

    def execute(self, conn: Connection, rows: list[dict[str, Any]]) -> None:
        """Insert rows (dicts by column name; a missing column is NULL) in ``conn``'s
        transaction; through SQLAlchemy Core for a driver whose parameter style it does not know."""
        if self.sql is None:
            conn.execute(self.table.insert(), rows)
            return
        values = [
            tuple(row.get(name) if f is None else f(row.get(name)) for name, f in self._convert)
            for row in rows
        ]
        conn.connection.cursor().executemany(self.sql, values)
