"""Durable storage of robot messages: file first, then the database row, then the ACK."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

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
        sid = str(message.session_id)
        with self.factory() as db:
            session = db.get(InspectionSession, sid)
            if message.type is MessageType.SESSION_START:
                if session is not None:
                    self._check_owner(session, robot_id)
                    return StoreResult("duplicate")
            elif session is None:
                raise IngestError(f"session {sid} is unknown: send SESSION_START first")
            else:
                self._check_owner(session, robot_id)
            if db.get(ReceivedMessage, (sid, message.seq)) is not None:
                return StoreResult("duplicate")
            ended = self._add_rows(db, message, sid, robot_id, session)
            try:
                db.commit()
            except IntegrityError:
                db.rollback()
                return StoreResult("duplicate")
        return StoreResult("stored", session_ended=ended)

    @staticmethod
    def _check_owner(session: InspectionSession, robot_id: int | None) -> None:
        if session.robot_id is not None and robot_id is not None and session.robot_id != robot_id:
            raise IngestError(f"session {session.id} belongs to another robot")

    def _add_rows(
        self,
        db: Session,
        message: Message,
        sid: str,
        robot_id: int | None,
        session: InspectionSession | None,
    ) -> bool:
        meta = message.meta
        pose = meta.get("pose") or {}
        mtype = message.type
        if mtype is MessageType.SESSION_START:
            db.add(
                InspectionSession(
                    id=sid,
                    robot_id=robot_id,
                    structure=meta["structure"],
                    operator=meta.get("operator", ""),
                    calibration=meta.get("calibration", {}),
                )
            )
            db.flush()
        db.add(ReceivedMessage(session_id=sid, seq=message.seq, type=mtype.name))
        if mtype is MessageType.FRAME:
            rel = self.files.frame_relpath(sid, message.seq)
            self.files.write(rel, message.payload)
            db.add(
                Frame(
                    session_id=sid,
                    seq=message.seq,
                    timestamp=message.timestamp,
                    width=meta["width"],
                    height=meta["height"],
                    path=rel,
                    size_bytes=len(message.payload),
                    pose_x=pose.get("x"),
                    pose_y=pose.get("y"),
                    pose_yaw=pose.get("yaw"),
                )
            )
        elif mtype is MessageType.CLOUD:
            rel = self.files.cloud_relpath(sid, message.seq, meta["encoding"])
            self.files.write(rel, message.payload)
            intrinsics = {k: meta[k] for k in ("fx", "fy", "cx", "cy") if k in meta}
            db.add(
                Cloud(
                    session_id=sid,
                    seq=message.seq,
                    timestamp=message.timestamp,
                    encoding=meta["encoding"],
                    width=meta["width"],
                    height=meta["height"],
                    intrinsics=intrinsics,
                    path=rel,
                    size_bytes=len(message.payload),
                    pose_x=pose.get("x"),
                    pose_y=pose.get("y"),
                    pose_yaw=pose.get("yaw"),
                )
            )
        elif mtype is MessageType.TELEMETRY:
            db.add(
                TelemetrySample(
                    session_id=sid, seq=message.seq, timestamp=message.timestamp, data=meta
                )
            )
        elif mtype is MessageType.SESSION_END:
            assert session is not None
            session.status = SessionStatus.ended
            session.ended_at = utcnow()
            session.end_reason = meta.get("reason", "completed")
            return True
        return False

