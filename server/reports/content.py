"""The inspection report's content, gathered from the database and the result files.

One function builds it (:func:`build_report`); ``report.json`` is this dict, the PDF
(:mod:`server.reports.pdf`) and ``defects.csv`` (:mod:`server.reports.tables`) are views of it.
A session without mosaic, map or detection gets a report that says so.
"""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from processing.coverage import CoverageParams
from processing.detection.defects import RESOLVED_PX
from server.reports.condition import element_condition
from server.reports.coverage import QualityCache, session_coverage
from server.reports.fields import CONDITION_STATES, GENERATOR
from server.reports.visits import visit_changes
from server.storage.files import SessionFiles
from server.storage.models import (
    Cloud,
    Defect,
    Frame,
    InspectionSession,
    Job,
    JobState,
    Structure,
    TelemetrySample,
)
from server.storage.spans import duration_s

STAGES = {"stitch": "mosaic", "map": "3D map", "detect": "defect detection"}


def build_report(
    db: Session,
    files: SessionFiles,
    session_id: str,
    *,
    base_url: str = "",
    coverage: CoverageParams | None = None,
) -> dict[str, Any]:
    """Everything the report of one session shows, as JSON-ready data (with ``coverage``:
    the surface imaged well enough and its holes, judged by those parameters)."""
    s = db.get(InspectionSession, session_id)
    if s is None:
        raise KeyError(session_id)
    jobs = list(db.scalars(select(Job).where(Job.session_id == session_id).order_by(Job.id)))
    latest = {j.kind: j for j in jobs}  # the newest job of each kind
    # the newest finished run of each kind: its results are the session's (a later run that
    # failed or was cancelled left them as they were)
    done = {j.kind: j for j in jobs if j.state == JobState.done}
    results_dir = files.results_dir(session_id)
    world = read_json(results_dir / "mosaic.json") if "stitch" in done else None
    listed_source = "mosaic" if world is not None else "frame"
    defects = list(
        db.scalars(
            select(Defect)
            .where(Defect.session_id == session_id, Defect.source == listed_source)
            .order_by(Defect.number.is_(None), Defect.number, Defect.id)
        )
    )
    resolved = [d for d in defects if _resolved(d, s.calibration)]
    unresolved = len(defects) - len(resolved)
    records = [_defect_record(d, d.number or i + 1, base_url) for i, d in enumerate(resolved)]
    counts = {
        m.__tablename__: db.scalar(
            select(func.count()).select_from(m).where(m.session_id == session_id)
        )
        or 0
        for m in (Frame, Cloud, TelemetrySample)
    }
    notes = _notes(latest, done, listed_source == "frame" and bool(defects))
    if unresolved:
        notes.append(
            f"{unresolved} detections below the camera's resolution (under {RESOLVED_PX:g} px) "
            "are not listed."
        )
    return {
        "generator": GENERATOR,
        "generated_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "cover": _cover(s),
        "summary": _summary(db, s, counts, records, world, results_dir, done),
        "defects": records,
        "defect_source": listed_source,
        "results": {k: j.result for k, j in done.items()},
        "parameters": {k: j.result.get("params", {}) for k, j in done.items() if k in STAGES},
        "jobs": [_job_record(j) for j in jobs],
        "missing": [k for k in STAGES if k not in done],
        "notes": notes,
        "files": _files(results_dir, base_url, session_id),
        "coverage": _coverage(db, files, session_id, coverage) if coverage else None,
        "calibration": s.calibration,
        "changes_since": _changes_since(db, files, s),
        "element_condition": _element_condition(db, s),
    }


def _changes_since(db: Session, files: SessionFiles, s: InspectionSession) -> dict[str, Any] | None:
    """What changed since the structure's previous inspection (None without one); places
    the session on the structure first, so the element condition below uses that place."""
    if s.structure_id is None:
        return None
    changes = visit_changes(db, files, s)
    return changes if changes["previous_session_id"] else None


def _element_condition(db: Session, s: InspectionSession) -> dict[str, Any] | None:
    """The AASHTO element condition table of the session's structure from this session
    (None when it inspects no structure on record)."""
    structure = db.get(Structure, s.structure_id) if s.structure_id is not None else None
    if structure is None:
        return None
    table, unplaced = element_condition(db, structure, s)
    return {
        "structure_id": structure.id,
        "structure": structure.name,
        "owner_id": structure.owner_id,
        "elements": [c.as_dict() for c in table],
        "unplaced_defects": unplaced,
    }


def _cover(s: InspectionSession) -> dict[str, Any]:
    """The report's cover: what was inspected, where, when, by whom."""
    return {
        "structure": s.structure,
        "location": s.location,
        "date": s.started_at.date().isoformat(),
        "started_at": _iso(s.started_at),
        "ended_at": _iso(s.ended_at),
        "operator": s.operator,
        "robot": s.robot.name if s.robot else None,
        "session_id": s.id,
        "status": s.status.value,
        "end_reason": s.end_reason,
        "notes": s.notes,
    }


def _job_record(j: Job) -> dict[str, Any]:
    return {
        "id": j.id,
        "kind": j.kind,
        "state": j.state.value,
        "error": j.error,
        "finished_at": _iso(j.finished_at),
    }


def _notes(latest: dict[str, Job], done: dict[str, Job], per_frame: bool) -> list[str]:
    """What the report's reader must know: stages with no result and why, frames and
    clouds left out, defects listed per frame (``per_frame``: no mosaic)."""
    notes = [
        f"No {label}: {_why_missing(latest.get(kind))}"
        for kind, label in STAGES.items()
        if kind not in done
    ]
    for kind, key, what in (
        (
            "stitch",
            "skipped_frames",
            "frames left out of the mosaic (unreadable or of another size)",
        ),
        ("map", "skipped_clouds", "ToF clouds left out of the 3D map (unreadable or empty)"),
    ):
        seqs = (done[kind].result or {}).get(key) if kind in done else None
        if seqs:
            shown = ", ".join(str(q) for q in seqs[:20]) + (", …" if len(seqs) > 20 else "")
            notes.append(f"{what[0].upper()}{what[1:]}: {len(seqs)} (seq {shown}).")
    if per_frame:
        notes.append(
            "Defects are listed per camera frame (no mosaic): one defect seen in overlapping "
            "frames appears more than once."
        )
    return notes


def _coverage(
    db: Session, files: SessionFiles, session_id: str, params: CoverageParams
) -> dict[str, Any]:
    """The coverage summary: areas, frames not counted and why, holes (largest first)."""
    cov = session_coverage(db, files, QualityCache(), session_id, params, with_grid=False)
    reasons: dict[str, int] = {}
    for f in cov.pop("frames"):
        if f["why_not"]:
            reasons[f["why_not"]] = reasons.get(f["why_not"], 0) + 1
    return cov | {"frames_not_counted_by_reason": reasons}


def _why_missing(job: Job | None) -> str:
    if job is None:
        return "the job has not been run for this session."
    if job.state == JobState.failed:
        return f"the job failed ({job.error})."
    return f"the job is {job.state.value}."


def _iso(t: datetime | None) -> str | None:
    return t.isoformat(timespec="seconds") if t is not None else None


def read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _resolved(d: Defect, calibration: dict[str, Any] | None) -> bool:
    """Whether a defect is at least :data:`RESOLVED_PX` camera pixels long (a crack) or
    that squared in area (corrosion); one drawn by a reviewer always counts."""
    px_per_m = float((calibration or {}).get("camera", {}).get("px_per_m") or 0)
    if d.drawn_by is not None or px_per_m <= 0:
        return True
    min_mm = RESOLVED_PX * 1000.0 / px_per_m
    if d.defect_class == "crack" and d.length_mm is not None:
        return d.length_mm >= min_mm
    if d.defect_class == "corrosion" and d.area_mm2 is not None:
        return d.area_mm2 >= min_mm**2
    return True


def _defect_record(d: Defect, number: int, base_url: str) -> dict[str, Any]:
    mean_width_mm = (
        d.mean_width_px * d.max_width_mm / d.max_width_px
        if d.max_width_mm and d.max_width_px
        else None
    )
    rec: dict[str, Any] = {
        "number": number,
        "id": d.id,
        "defect_class": d.defect_class,
        "source": d.source,
        "drawn_by": d.drawn_by,
        "frame_seq": d.frame_seq,
        "length_mm": d.length_mm,
        "max_width_mm": d.max_width_mm,
        "mean_width_mm": mean_width_mm,
        "area_mm2": d.area_mm2,
        "world_x_m": d.world_x_m,
        "world_y_m": d.world_y_m,
        "world_w_m": d.world_w_m,
        "world_h_m": d.world_h_m,
        "bbox_x": d.bbox_x,
        "bbox_y": d.bbox_y,
        "bbox_w": d.bbox_w,
        "bbox_h": d.bbox_h,
        "area_px": d.area_px,
        "length_px": d.length_px,
        "max_width_px": d.max_width_px,
        "orientation_deg": d.orientation_deg,
        "review_status": d.review_status,
        "condition_state": d.condition_state,
        "comment": d.comment,
        "reviewed_by": d.reviewed_by,
        "reviewed_at": _iso(d.reviewed_at),
    }
    rec["thumbnail_url"] = f"{base_url}/api/sessions/{d.session_id}/defects/{d.id}/thumbnail.jpg"
    # the dashboard opens on this defect, its frames a click away (the PDF links its number)
    rec["dashboard_url"] = f"{base_url}/#/session/{d.session_id}/defect/{number}"
    return rec


def _summary(
    db: Session,
    s: InspectionSession,
    counts: dict[str, int],
    records: list[dict[str, Any]],
    world: dict[str, Any] | None,
    results_dir: Path,
    done: dict[str, Job],
) -> dict[str, Any]:
    kept = [r for r in records if r["review_status"] != "rejected"]
    cracks = [r for r in kept if r["defect_class"] == "crack"]
    return {
        "frames": counts["frames"],
        "clouds": counts["clouds"],
        "telemetry_samples": counts["telemetry"],
        "duration_s": duration_s(db, s),
        "distance_travelled_m": _distance_travelled(db, s.id),
        "area_covered_m2": _area_covered(results_dir, world),
        "mosaic_size_px": [world["width_px"], world["height_px"]] if world else None,
        "map_points": done["map"].result.get("points") if "map" in done else None,
        "defects": len(records),
        "defects_rejected": len(records) - len(kept),
        "defects_by_class": {
            c: sum(1 for r in kept if r["defect_class"] == c) for c in ("crack", "corrosion")
        },
        "defects_by_condition_state": {
            cs: sum(1 for r in kept if r["condition_state"] == cs) for cs in CONDITION_STATES
        }
        | {"not rated": sum(1 for r in kept if r["condition_state"] is None)},
        "defects_by_review": {
            st: sum(1 for r in records if r["review_status"] == st)
            for st in ("confirmed", "unreviewed", "rejected")
        },
        "longest_crack_mm": max(
            (r["length_mm"] for r in cracks if r["length_mm"] is not None), default=None
        ),
        "widest_crack_mm": max(
            (r["max_width_mm"] for r in cracks if r["max_width_mm"] is not None), default=None
        ),
        "total_crack_length_mm": sum(r["length_mm"] for r in cracks if r["length_mm"] is not None)
        if cracks
        else 0.0,
        "corroded_area_mm2": sum(
            r["area_mm2"] or 0.0 for r in kept if r["defect_class"] == "corrosion"
        ),
    }


def _distance_travelled(db: Session, session_id: str) -> float | None:
    """Length of the odometry path (telemetry poses, else frame poses), metres."""
    rows = db.execute(
        select(TelemetrySample.data)
        .where(TelemetrySample.session_id == session_id)
        .order_by(TelemetrySample.seq)
    )
    xy = [
        (p["x"], p["y"])
        for (data,) in rows
        if isinstance(p := data.get("pose"), dict) and "x" in p and "y" in p
    ]
    if len(xy) < 2:
        xy = [
            (x, y)
            for x, y in db.execute(
                select(Frame.pose_x, Frame.pose_y)
                .where(Frame.session_id == session_id, Frame.pose_x.is_not(None))
                .order_by(Frame.seq)
            )
        ]
    if len(xy) < 2:
        return None
    return float(np.linalg.norm(np.diff(np.asarray(xy, dtype=np.float64), axis=0), axis=1).sum())


def _area_covered(results_dir: Path, world: dict[str, Any] | None) -> float | None:
    """Surface area the mosaic covers (m²), from its coverage mask, streamed by libvips."""
    if world is None or not world.get("world_referenced"):
        return None
    path = results_dir / "mosaic_coverage.png"
    if not path.is_file():
        return None
    import pyvips

    mask = pyvips.Image.new_from_file(str(path), access="sequential")
    covered_px = mask.avg() / 255.0 * mask.width * mask.height
    return float(covered_px / float(world["px_per_m"]) ** 2)


def _files(results_dir: Path, base_url: str, session_id: str) -> dict[str, str]:
    api = f"{base_url}/api/sessions/{session_id}"
    out = {
        "report_pdf": f"{api}/report.pdf",
        "report_json": f"{api}/report.json",
        "defects_csv": f"{api}/defects.csv",
        "defects_json": f"{api}/defects.json",
        "mcap": f"{api}/export.mcap",
    }
    for name, key in (
        ("mosaic_overview.png", "mosaic_overview"),
        ("mosaic.png", "mosaic"),
        ("mosaic.dzi", "mosaic_dzi"),
        ("map.ply", "map_ply"),
        ("trajectory.tum", "trajectory_tum"),
    ):
        if (results_dir / name).is_file():
            out[key] = f"{api}/results/{name}"
    return out
