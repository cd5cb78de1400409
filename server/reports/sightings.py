"""Where a defect was seen: the camera frames whose footprint holds its centre, each with
its time, the robot's pose and the telemetry sample nearest that moment, in time order.
This is what a reviewer replays to check a defect against the moment of capture."""

from __future__ import annotations

from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from processing.coverage import footprint
from processing.poses import compose_se2
from server.reports.timeline import inside_convex
from server.storage.models import Defect, Frame, InspectionSession, TelemetrySample


def nearest_telemetry(db: Session, session_id: str, t: float) -> dict[str, Any] | None:
    """The telemetry sample nearest time ``t`` (robot clock), with its time offset."""
    base = select(TelemetrySample).where(TelemetrySample.session_id == session_id)
    before = db.scalar(
        base.where(TelemetrySample.timestamp <= t).order_by(TelemetrySample.timestamp.desc())
    )
    after = db.scalar(
        base.where(TelemetrySample.timestamp >= t).order_by(TelemetrySample.timestamp)
    )
    best = min(
        (s for s in (before, after) if s is not None),
        key=lambda s: abs(s.timestamp - t),
        default=None,
    )
    if best is None:
        return None
    return {"seq": best.seq, "dt_s": best.timestamp - t, "data": best.data}


def defect_sightings(db: Session, defect: Defect) -> list[dict[str, Any]]:
    """The frames a defect was seen in (its own frame for a frame defect, every frame whose
    footprint holds its centre when it is placed on the structure), oldest first."""
    s = db.get(InspectionSession, defect.session_id)
    camera = (s.calibration or {}).get("camera", {}) if s is not None else {}
    px_per_m = float(camera.get("px_per_m") or 0)
    T_rc = np.asarray(camera.get("T_robot_camera", [0.0, 0.0, 0.0]), dtype=np.float64)
    frames = list(
        db.scalars(select(Frame).where(Frame.session_id == defect.session_id).order_by(Frame.seq))
    )
    start = min((f.timestamp for f in frames), default=0.0)
    seen = []
    placed = defect.world_x_m is not None and defect.world_y_m is not None and px_per_m > 0
    centre = (
        np.array(
            [
                defect.world_x_m + (defect.world_w_m or 0.0) / 2,
                defect.world_y_m + (defect.world_h_m or 0.0) / 2,
            ]
        )
        if placed
        else None
    )
    for f in frames:
        own = defect.source == "frame" and f.seq == defect.frame_seq
        hit = own
        if not hit and centre is not None and f.pose_x is not None:
            cam = compose_se2(np.array([f.pose_x, f.pose_y, f.pose_yaw or 0.0]), T_rc)
            hit = bool(
                inside_convex(centre, footprint(cam, px_per_m, (f.width, f.height))[None])[0, 0]
            )
        if hit:
            seen.append(
                {
                    "seq": f.seq,
                    "timestamp": f.timestamp,
                    "t_s": f.timestamp - start,
                    "pose": None
                    if f.pose_x is None
                    else {"x": f.pose_x, "y": f.pose_y, "yaw": f.pose_yaw},
                    "image_url": f"/api/sessions/{f.session_id}/frames/{f.seq}/image",
                    "telemetry": nearest_telemetry(db, f.session_id, f.timestamp),
                }
            )
    return seen
