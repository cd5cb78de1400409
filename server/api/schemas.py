"""Pydantic schemas of the REST API."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator


def _encodable(text: str) -> str:
    """Text that either database can store: valid UTF-8 (JSON allows lone surrogates such as
    \\ud800) without NUL characters (PostgreSQL's text cannot hold them)."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError("text must be valid Unicode (no lone surrogates)") from None
    if "\x00" in text:
        raise ValueError("text must not hold NUL characters (\\u0000)")
    return text


Text = Annotated[str, AfterValidator(_encodable)]


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
    attempt: int = Field(
        description="attempts that have taken the job (a lost worker's job is taken again)"
    )
    worker: str | None = Field(description="where the latest attempt runs or ran")


class JobCreate(BaseModel):
    kind: Literal["stitch", "map", "detect", "export"]
    method: Literal["proposed", "learned"] | None = Field(
        default=None,
        description="detect only: the crack detector (default: the station's detect_method)",
    )

    @model_validator(mode="after")
    def _method_for_detect_only(self) -> JobCreate:
        if self.method is not None and self.kind != "detect":
            raise ValueError("method applies to detect jobs only")
        return self


class ResultsCover(BaseModel):
    """What a session's newest processing read: the frames, clouds and telemetry stored
    when it was queued."""

    frames: int
    clouds: int
    telemetry: int
    current: bool = Field(
        description="whether it covers everything the session holds now (false: data came "
        "after it, and the session is processed again)"
    )


class SessionPublic(ORM):
    id: str
    structure: str
    operator: str
    location: str = ""
    notes: str = ""
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
    imported: bool = Field(default=False, description="imported from an MCAP log")
    duration_s: float = Field(
        default=0.0, description="how long the inspection lasted (its data's span, robot clock)"
    )
    calibration: dict[str, Any] = Field(default_factory=dict)
    jobs: list[JobPublic] = Field(default_factory=list)
    results_cover: ResultsCover | None = Field(
        default=None, description="what its results were made from (None: not processed)"
    )


class SessionUpdate(BaseModel):
    """What a user may correct about a session (for the report's cover)."""

    model_config = ConfigDict(extra="forbid")
    structure: Text | None = Field(default=None, min_length=1, max_length=200)
    location: Text | None = Field(default=None, max_length=200)
    operator: Text | None = Field(default=None, max_length=200)
    notes: Text | None = Field(default=None, max_length=10_000)


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


class CloudPublic(ORM):
    seq: int
    timestamp: float
    encoding: str
    width: int
    height: int
    intrinsics: dict[str, Any]
    size_bytes: int
    pose_x: float | None
    pose_y: float | None
    pose_yaw: float | None


class CloudsPublic(BaseModel):
    data: list[CloudPublic]
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
    number: int | None = Field(
        default=None,
        description="the defect's number in its session (per source, in order along the "
        "structure): what the dashboard, 3D view, PDF, CSV and MCAP show",
    )
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
    confidence: float | None = Field(
        default=None,
        description="how sure the detector is: the calibrated probability that this is a true "
        "defect (None: drawn by hand, or a detector without calibration)",
    )
    review_status: str
    condition_state: str | None
    defect_code: int | None = Field(
        default=None, description="the reviewer's AASHTO defect code (None: the class's)"
    )
    comment: str
    reviewed_by: str | None = None
    reviewed_at: datetime | None = None
    drawn_by: str | None = Field(default=None, description="who drew it by hand, if someone did")


ReviewStatus = Literal["unreviewed", "confirmed", "rejected"]
ConditionState = Literal["CS1", "CS2", "CS3", "CS4"]


class DefectReview(BaseModel):
    """An inspector's verdict on one defect; fields left out stay as they are."""

    model_config = ConfigDict(extra="forbid")
    review_status: ReviewStatus | None = None
    condition_state: ConditionState | None = None
    clear_condition_state: bool = Field(
        default=False, description="set the condition state back to none"
    )
    comment: Text | None = Field(default=None, max_length=2000)
    defect_code: Literal[0, 1000, 1010, 1020, 1900] | None = Field(
        default=None,
        description="AASHTO steel defect code (1000 corrosion, 1010 cracking, 1020 connection, "
        "1900 distortion); 0 returns to the class's",
    )


class DefectCreate(BaseModel):
    """A defect the detector missed, drawn by a reviewer as a box on the mosaic (pixels)."""

    model_config = ConfigDict(extra="forbid")
    defect_class: Literal["crack", "corrosion"]
    bbox_x: int = Field(ge=0, le=10_000_000)
    bbox_y: int = Field(ge=0, le=10_000_000)
    bbox_w: int = Field(ge=1, le=1_000_000)
    bbox_h: int = Field(ge=1, le=1_000_000)
    condition_state: ConditionState | None = None
    comment: Text = Field(default="", max_length=2000)


class DefectsPublic(BaseModel):
    data: list[DefectPublic]
    count: int


class Message(BaseModel):
    detail: str
