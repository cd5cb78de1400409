"""SQLAlchemy models: robots, inspection sessions, what they sent, jobs and defects."""

from __future__ import annotations

import enum
from datetime import datetime, timezone
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    DateTime,
    Enum,
    Float,
    ForeignKey,
    Integer,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship


def utcnow() -> datetime:
    """Timezone-aware now in UTC."""
    return datetime.now(timezone.utc)


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON, datetime: DateTime(timezone=True)}


class SessionStatus(str, enum.Enum):
    live = "live"
    ended = "ended"


class JobState(str, enum.Enum):
    queued = "queued"
    running = "running"
    done = "done"
    failed = "failed"
    cancelled = "cancelled"


class Robot(Base):
    __tablename__ = "robots"
    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Role(str, enum.Enum):
    viewer = "viewer"
    operator = "operator"
    admin = "admin"


class User(Base):
    __tablename__ = "users"
    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    password_hash: Mapped[str] = mapped_column(String(200))
    role: Mapped[Role] = mapped_column(Enum(Role, native_enum=False, length=16))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class UserPreferences(Base):
    """What a user keeps of the dashboard across browsers (the telemetry fields plotted,
    the Drive page's panels), by account name ("anonymous" while no account exists)."""

    __tablename__ = "user_preferences"
    user_name: Mapped[str] = mapped_column(String(200), primary_key=True)
    data: Mapped[dict[str, Any]] = mapped_column(default=dict)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)


class AuthToken(Base):
    """A bearer token handed out by POST /api/auth/token (stored only as a SHA-256 hash)."""

    __tablename__ = "auth_tokens"
    token_hash: Mapped[str] = mapped_column(String(64), primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    expires_at: Mapped[datetime]


class Structure(Base):
    """A structure an inspection team visits (a bridge, a span, a girder line)."""

    __tablename__ = "structures"
    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    owner_id: Mapped[str] = mapped_column(String(100), default="", server_default="")
    location: Mapped[str] = mapped_column(Text, default="", server_default="")
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Element(Base):
    """An AASHTO element of a structure: its number, quantity (m, m² or each by the element)
    and its extent, a rectangle in the structure's frame (metres)."""

    __tablename__ = "elements"
    id: Mapped[int] = mapped_column(primary_key=True)
    structure_id: Mapped[int] = mapped_column(
        ForeignKey("structures.id", ondelete="CASCADE"), index=True
    )
    number: Mapped[int] = mapped_column(Integer)
    name: Mapped[str] = mapped_column(String(200), default="", server_default="")
    quantity: Mapped[float]
    x0: Mapped[float]
    y0: Mapped[float]
    x1: Mapped[float]
    y1: Mapped[float]
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class InspectionSession(Base):
    __tablename__ = "inspection_sessions"
    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    robot_id: Mapped[int | None] = mapped_column(ForeignKey("robots.id"))
    structure: Mapped[str] = mapped_column(String(200))
    operator: Mapped[str] = mapped_column(String(200), default="")
    location: Mapped[str] = mapped_column(String(200), default="", server_default="")
    notes: Mapped[str] = mapped_column(Text, default="", server_default="")
    status: Mapped[SessionStatus] = mapped_column(
        Enum(SessionStatus, native_enum=False, length=16), default=SessionStatus.live
    )
    started_at: Mapped[datetime] = mapped_column(default=utcnow)
    ended_at: Mapped[datetime | None]
    end_reason: Mapped[str | None] = mapped_column(String(200))
    # the seq of the robot's SESSION_END (None: live, or ended by the station); once ended a
    # session stays ended and its end never moves (a trigger of migration 0008)
    end_seq: Mapped[int | None] = mapped_column(BigInteger)
    calibration: Mapped[dict[str, Any]] = mapped_column(default=dict)
    # the structure it inspects, and its datum: the pose (x, y, yaw) of the session's world
    # frame in the structure's
    structure_id: Mapped[int | None] = mapped_column(ForeignKey("structures.id"))
    datum: Mapped[dict[str, Any] | None]
    robot: Mapped[Robot | None] = relationship()


class ReceivedMessage(Base):
    """One row per (session, seq) stored: the guard that makes resends idempotent."""

    __tablename__ = "received_messages"
    session_id: Mapped[str] = mapped_column(
        ForeignKey("inspection_sessions.id", ondelete="CASCADE"), primary_key=True
    )
    seq: Mapped[int] = mapped_column(Integer, primary_key=True)
    type: Mapped[str] = mapped_column(String(20))
    received_at: Mapped[datetime] = mapped_column(default=utcnow)


class _PoseColumns:
    pose_x: Mapped[float | None] = mapped_column(Float)
    pose_y: Mapped[float | None] = mapped_column(Float)
    pose_yaw: Mapped[float | None] = mapped_column(Float)


class Frame(_PoseColumns, Base):
    __tablename__ = "frames"
    __table_args__ = (UniqueConstraint("session_id", "seq"),)
    id: Mapped[int] = mapped_column(primary_key=True)
    session_id: Mapped[str] = mapped_column(
        ForeignKey("inspection_sessions.id", ondelete="CASCADE"), index=True
    )
    seq: Mapped[int]
    timestamp: Mapped[float]
    width: Mapped[int]
    height: Mapped[int]
    path: Mapped[str] = mapped_column(String(500))
    size_bytes: Mapped[int]
    # where in a segment file; None: the whole file
    data_offset: Mapped[int | None] = mapped_column(BigInteger)


class Cloud(_PoseColumns, Base):
    __tablename__ = "clouds"
    __table_args__ = (UniqueConstraint("session_id", "seq"),)
    id: Mapped[int] = mapped_column(primary_key=True)
    session_id: Mapped[str] = mapped_column(
        ForeignKey("inspection_sessions.id", ondelete="CASCADE"), index=True
    )
    seq: Mapped[int]
    timestamp: Mapped[float]
    encoding: Mapped[str] = mapped_column(String(32))
    width: Mapped[int]
    height: Mapped[int]
    intrinsics: Mapped[dict[str, Any]] = mapped_column(default=dict)
    path: Mapped[str] = mapped_column(String(500))
    size_bytes: Mapped[int]
    # where in a segment file; None: the whole file
    data_offset: Mapped[int | None] = mapped_column(BigInteger)


class TelemetrySample(Base):
    __tablename__ = "telemetry"
    __table_args__ = (UniqueConstraint("session_id", "seq"),)
    id: Mapped[int] = mapped_column(primary_key=True)
    session_id: Mapped[str] = mapped_column(
        ForeignKey("inspection_sessions.id", ondelete="CASCADE"), index=True
    )
    seq: Mapped[int]
    timestamp: Mapped[float]
    data: Mapped[dict[str, Any]] = mapped_column(default=dict)


class Job(Base):
    __tablename__ = "jobs"
    id: Mapped[int] = mapped_column(primary_key=True)
    session_id: Mapped[str] = mapped_column(
        ForeignKey("inspection_sessions.id", ondelete="CASCADE"), index=True
    )
    kind: Mapped[str] = mapped_column(String(32))
    state: Mapped[JobState] = mapped_column(
        Enum(JobState, native_enum=False, length=16), default=JobState.queued
    )
    progress: Mapped[float] = mapped_column(default=0.0)
    message: Mapped[str] = mapped_column(Text, default="")
    error: Mapped[str | None] = mapped_column(Text)
    params: Mapped[dict[str, Any]] = mapped_column(default=dict)
    result: Mapped[dict[str, Any]] = mapped_column(default=dict)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    # the lease (server/jobs/leases.py): which attempt holds the job, where, and its last sign
    # of life; when the station last handed the job to the queue
    attempt: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    worker: Mapped[str | None] = mapped_column(String(200))
    heartbeat_at: Mapped[datetime | None]
    dispatched_at: Mapped[datetime | None]


class Defect(Base):
    __tablename__ = "defects"
    id: Mapped[int] = mapped_column(primary_key=True)
    session_id: Mapped[str] = mapped_column(
        ForeignKey("inspection_sessions.id", ondelete="CASCADE"), index=True
    )
    job_id: Mapped[int | None] = mapped_column(ForeignKey("jobs.id", ondelete="SET NULL"))
    source: Mapped[str] = mapped_column(String(16), default="mosaic")
    number: Mapped[int | None] = mapped_column(Integer)  # 1.. per session and source
    frame_seq: Mapped[int | None] = mapped_column(Integer)
    defect_class: Mapped[str] = mapped_column(String(16))
    bbox_x: Mapped[int]
    bbox_y: Mapped[int]
    bbox_w: Mapped[int]
    bbox_h: Mapped[int]
    area_px: Mapped[int]
    length_px: Mapped[float]
    max_width_px: Mapped[float]
    mean_width_px: Mapped[float]
    orientation_deg: Mapped[float]
    length_mm: Mapped[float | None]
    max_width_mm: Mapped[float | None]
    area_mm2: Mapped[float | None]
    world_x_m: Mapped[float | None]
    world_y_m: Mapped[float | None]
    world_w_m: Mapped[float | None]
    world_h_m: Mapped[float | None]
    # how sure the detector is (calibrated P(a true defect)); None: drawn, or no calibration
    confidence: Mapped[float | None]
    review_status: Mapped[str] = mapped_column(String(16), default="unreviewed")
    condition_state: Mapped[str | None] = mapped_column(String(8))
    # the AASHTO defect code a reviewer set (None: the class's, crack 1010, corrosion 1000)
    defect_code: Mapped[int | None] = mapped_column(Integer)
    comment: Mapped[str] = mapped_column(Text, default="")
    reviewed_by: Mapped[str | None] = mapped_column(String(200))
    reviewed_at: Mapped[datetime | None]
    drawn_by: Mapped[str | None] = mapped_column(String(200))  # a defect a reviewer drew
