"""Fields every report format shares: defect columns, condition states, the generator."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from server.storage.models import Defect

GENERATOR = "steelscan 0.1.0"
# how an imported session's notes name the file it came from (its robot is none)
IMPORTED_FROM = "Imported from"
CONDITION_STATES = ("CS1", "CS2", "CS3", "CS4")
CONDITION_MEANING = {"CS1": "good", "CS2": "fair", "CS3": "poor", "CS4": "severe"}
# what a defect's one position (``world_x_m``, ``world_y_m``) is, wherever it is shown
POSITION_MEANING = "the corner of the defect's box nearest the structure's origin"
DEFECT_FIELDS = (
    "number",
    "id",
    "defect_class",
    "source",
    "drawn_by",
    "frame_seq",
    "length_mm",
    "max_width_mm",
    "mean_width_mm",
    "area_mm2",
    "world_x_m",
    "world_y_m",
    "world_w_m",
    "world_h_m",
    "bbox_x",
    "bbox_y",
    "bbox_w",
    "bbox_h",
    "area_px",
    "length_px",
    "max_width_px",
    "orientation_deg",
    "review_status",
    "condition_state",
    "comment",
    "reviewed_by",
    "reviewed_at",
)

# what a defect's stored record holds (all of its row but the session and job it belongs to)
RECORD_FIELDS = tuple(
    c.key for c in Defect.__table__.columns if c.key not in ("session_id", "job_id")
)


def defect_record(d: Defect) -> dict[str, Any]:
    """A defect's row as JSON-ready data (times as ISO 8601), as the REST API gives it."""
    out: dict[str, Any] = {}
    for key in RECORD_FIELDS:
        value = getattr(d, key)
        out[key] = value.isoformat() if isinstance(value, datetime) else value
    return out
