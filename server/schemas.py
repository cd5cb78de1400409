"""Pydantic schemas of the REST API."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


class ORM(BaseModel):
    model_config = ConfigDict(from_attributes=True)


class JobPublic(ORM):
    id: int
    session_id: str
    kind: str
    state: str
    progress: float
    message: str
    error: str | None
    result: dict[str, Any]
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class JobCreate(BaseModel):
    kind: Literal["stitch", "map", "detect"]


class SessionPublic(ORM):
    id: str
    structure: str
    operator: str
    status: str
    started_at: datetime
    ended_at: datetime | None
    end_reason: str | None
    frames: int = 0
    clouds: int = 0
    telemetry: int = 0
    defects: int = 0
    frame_defects: int = 0
    robot_name: str | None = None
    calibration: dict[str, Any] = Field(default_factory=dict)
    jobs: list[JobPublic] = Field(default_factory=list)


class SessionsPublic(BaseModel):
    data: list[SessionPublic]
    count: int


class FramePublic(ORM):
    seq: int
    timestamp: float
    width: int
    height: int
    size_bytes: int
    pose_x: float | None
    pose_y: float | None
    pose_yaw: float | None


class FramesPublic(BaseModel):
    data: list[FramePublic]
    count: int


class TelemetryPublic(ORM):
    seq: int
    timestamp: float
    data: dict[str, Any]


class TelemetryListPublic(BaseModel):
    data: list[TelemetryPublic]
    count: int


class DefectPublic(ORM):
    id: int
    defect_class: str
    source: str
    frame_seq: int | None = None
    bbox_x: int
    bbox_y: int
    bbox_w: int
    bbox_h: int
    area_px: int
    length_px: float
    max_width_px: float
    mean_width_px: float
    orientation_deg: float
    length_mm: float | None
    max_width_mm: float | None
    area_mm2: float | None
    world_x_m: float | None
    world_y_m: float | None
    world_w_m: float | None
    world_h_m: float | None
    review_status: str
    condition_state: str | None
    comment: str


class DefectsPublic(BaseModel):
    data: list[DefectPublic]
    count: int


class Message(BaseModel):
    detail: str
