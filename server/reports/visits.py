"""What changed on a structure since its previous inspection: each defect of this session
matched to the previous session's by position in the structure's frame
(:mod:`processing.history.visits`), and the elements whose condition worsened."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from processing.history.align import AlignmentError, AlignParams, align_visits, world_transform
from processing.history.map_align import MapAlignmentError, align_maps
from processing.history.visits import DefectChange, VisitDefect, match_visits
from processing.poses import compose_se2, se2_to_se3
from server.reports.condition import element_condition, structure_box
from server.storage.files import SessionFiles
from server.storage.models import Defect, InspectionSession, Job, JobState, Structure


def previous_session(db: Session, s: InspectionSession) -> InspectionSession | None:
    """The structure's latest session before ``s``."""
    if s.structure_id is None:
        return None
    return db.scalars(
        select(InspectionSession)
        .where(
            InspectionSession.structure_id == s.structure_id,
            InspectionSession.started_at < s.started_at,
        )
        .order_by(InspectionSession.started_at.desc())
        .limit(1)
    ).first()


@dataclass(frozen=True)
class _Mosaic:
    """A session's mosaic overview and where its pixels are in its world frame."""

    job_id: int  # the stitch job that made it
    image: np.ndarray
    origin_m: tuple[float, float]
    px_per_m: float  # overview pixels per metre


def _stitch_job(db: Session, session_id: str) -> Job | None:
    return _job(db, session_id, "stitch")


def _mosaic(db: Session, files: SessionFiles, session_id: str) -> _Mosaic | None:
    job = _stitch_job(db, session_id)
    if job is None or not job.result.get("overview_path"):
        return None
    r = job.result
    origin = (float(r["origin_m"][0]), float(r["origin_m"][1]))
    results = files.results_dir(session_id)
    full = results / "mosaic.png"
    if full.exists():  # the full mosaic shrunk to the alignment's pixel budget: a long
        # strip keeps more of its fine texture than in the fixed-size overview
        image, scale = _shrunk(full, AlignParams().feature_pixels)
    else:
        image = cv2.imread(str(results / Path(r["overview_path"]).name), cv2.IMREAD_COLOR)
        scale = float(r.get("overview_scale", 1.0))
    if image is None:
        return None
    return _Mosaic(job.id, image, origin, float(r["px_per_m"]) * scale)


def _shrunk(path: Path, pixels: int) -> tuple[np.ndarray | None, float]:
    """An image of at most about ``pixels`` pixels (BGR) from a large PNG without decoding
    it whole at full size, and its scale."""
    import pyvips

    try:
        header = pyvips.Image.new_from_file(str(path))
        width, height = header.width, header.height
        s = min(1.0, float(np.sqrt(pixels / (width * height))))
        small = pyvips.Image.thumbnail(
            str(path), max(1, round(width * s)), height=height, size="down"
        )
        rgb = np.ndarray(
            buffer=small.write_to_memory(),
            dtype=np.uint8,
            shape=(small.height, small.width, small.bands),
        )
    except pyvips.Error:
        return None, 1.0
    bgr = cv2.cvtColor(np.ascontiguousarray(rgb[..., :3]), cv2.COLOR_RGB2BGR)
    return bgr, small.width / width


def _pose(datum: dict[str, Any] | None) -> dict[str, float]:
    d = datum or {}
    return {k: float(d.get(k, 0.0)) for k in ("x", "y", "yaw")}


def register_visit(
    db: Session, files: SessionFiles, before: InspectionSession, after: InspectionSession
) -> dict[str, Any] | None:
    """AFTER's datum refined by registering its mosaic to BEFORE's (robust to lighting and
    new rust, :func:`processing.history.align.align_visits`): AFTER's world frame placed in
    BEFORE's, then on the structure through BEFORE's datum. None without both mosaics or
    when they do not align."""
    mb, ma = _mosaic(db, files, before.id), _mosaic(db, files, after.id)
    if mb is None or ma is None:
        return None
    try:
        al = align_visits(mb.image, ma.image)
    except AlignmentError:
        return None
    pose, rigid_rms = world_transform(
        al.after_to_before,
        (ma.image.shape[1], ma.image.shape[0]),
        ma.origin_m,
        ma.px_per_m,
        mb.origin_m,
        mb.px_per_m,
    )
    d = _pose(before.datum)
    x, y, yaw = compose_se2(np.array([d["x"], d["y"], d["yaw"]]), pose)
    return {
        "previous_session_id": before.id,
        "datum": {"x": round(float(x), 6), "y": round(float(y), 6), "yaw": round(float(yaw), 8)},
        "residual_mm": round(al.residual_px / mb.px_per_m * 1000, 3),
        "rigid_rms_mm": round(rigid_rms * 1000, 3),
        "overlap": round(al.overlap, 4),
        "map": _maps_agree(db, files, before, after, pose),
    }


def _job(db: Session, session_id: str, kind: str) -> Job | None:
    return db.scalars(
        select(Job)
        .where(Job.session_id == session_id, Job.kind == kind, Job.state == JobState.done)
        .order_by(Job.id.desc())
        .limit(1)
    ).first()


def _map_points(db: Session, files: SessionFiles, session_id: str) -> np.ndarray | None:
    if _job(db, session_id, "map") is None:
        return None
    path = files.results_dir(session_id) / "map.ply"
    if not path.exists():
        return None
    import open3d as o3d

    points = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    return points if len(points) else None


def _maps_agree(
    db: Session,
    files: SessionFiles,
    before: InspectionSession,
    after: InspectionSession,
    pose: np.ndarray,
) -> dict[str, Any] | None:
    """How the two visits' 3D maps agree once the mosaics' pose (AFTER's world in BEFORE's)
    places them (:func:`processing.history.map_align.align_maps`): the residual across the
    surfaces, the share of AFTER's map on BEFORE's, how far the maps moved the mosaics'
    pose, and AFTER's height and tilt in BEFORE's frame. None without both maps or when
    they do not align."""
    pb, pa = _map_points(db, files, before.id), _map_points(db, files, after.id)
    if pb is None or pa is None:
        return None
    try:
        found = align_maps(pb, pa, se2_to_se3(*(float(v) for v in pose)))
    except MapAlignmentError:
        return None
    T = found.after_to_before
    return {
        "rmse_mm": round(found.rmse_m * 1000, 2),
        "fitness": round(found.fitness, 3),
        "correction_mm": round(found.correction_m * 1000, 2),
        "height_mm": round(float(T[2, 3]) * 1000, 2),
        "tilt_deg": round(float(np.degrees(np.arccos(np.clip(T[2, 2], -1, 1)))), 3),
        "unobserved_directions": found.degenerate,
    }


def place_session(
    db: Session, files: SessionFiles, s: InspectionSession, before: InspectionSession
) -> dict[str, Any] | None:
    """Place ``s`` on its structure through the previous visit ``before``: its datum as
    marked (where the robot was set down) refined by :func:`register_visit`, stored on the
    session (``datum`` x, y, yaw: the refined pose; ``marked``: as set; ``registration``:
    how it was found) so that its defects, its element condition and later visits use it.
    Registered once per pair of mosaics and BEFORE's placement; the registration, or None
    where the mosaics do not align (the marked datum stands)."""
    marked = _pose((s.datum or {}).get("marked", s.datum))
    mosaics = [
        j.id if j else None
        for kind in ("stitch", "map")
        for j in (_job(db, before.id, kind), _job(db, s.id, kind))
    ]
    key = [before.id, *mosaics, *_pose(before.datum).values()]
    done = (s.datum or {}).get("registration")
    if done is not None and done.get("key") == key:
        return done.get("result")
    result = register_visit(db, files, before, s)
    placed = result["datum"] if result else marked
    s.datum = {**placed, "marked": marked, "registration": {"key": key, "result": result}}
    db.commit()
    return result


def place(db: Session, files: SessionFiles, s: InspectionSession) -> None:
    """Place ``s`` and the structure's visits before it on the structure, oldest first
    (:func:`place_session`; each one registered once)."""
    chain = [s]
    while (before := previous_session(db, chain[-1])) is not None:
        chain.append(before)
    for after, before in zip(chain[-2::-1], chain[::-1], strict=False):
        place_session(db, files, after, before)


def visit_defects(db: Session, s: InspectionSession) -> list[VisitDefect]:
    """The visit's defects on its mosaic, not rejected, placed on the structure through
    its datum (those without a position left out)."""
    rows = db.scalars(
        select(Defect)
        .where(Defect.session_id == s.id, Defect.source == "mosaic")
        .where(Defect.review_status != "rejected")
        .order_by(Defect.number)
    ).all()
    out = []
    for d in rows:
        box = structure_box(d, s.datum)
        if box is not None:
            out.append(
                VisitDefect(d.id, d.defect_class, box, d.length_mm, d.max_width_mm, d.area_mm2)
            )
    return out


def side_record(v: VisitDefect, number: int | None) -> dict[str, Any]:
    """One visit's side of a change, as the REST answer gives it."""
    return {
        "defect_id": v.id,
        "number": number,
        "box_m": [round(x, 4) for x in v.box],
        "length_mm": v.length_mm,
        "width_mm": v.width_mm,
        "area_mm2": v.area_mm2,
    }


def _record(c: DefectChange, numbers: dict[int, int | None]) -> dict[str, Any]:
    def side(v: VisitDefect | None) -> dict[str, Any] | None:
        return None if v is None else side_record(v, numbers.get(v.id))

    kind = c.after or c.before
    assert kind is not None
    return {
        "status": c.status,
        "class": kind.defect_class,
        "before": side(c.before),
        "after": side(c.after),
        "parts_before": list(c.parts_before),
        "parts_after": list(c.parts_after),
        "length_change_mm": c.delta("length_mm"),
        "width_change_mm": c.delta("width_mm"),
        "area_change_mm2": c.delta("area_mm2"),
    }


def visit_changes(db: Session, files: SessionFiles, s: InspectionSession) -> dict[str, Any]:
    """The changes since the structure's previous session (none when there is none); the
    session is placed on the structure by registering its mosaic to the previous one's
    where both exist (:func:`place_session`), else by its datum as marked."""
    before = previous_session(db, s)
    out: dict[str, Any] = {
        "session_id": s.id,
        "structure_id": s.structure_id,
        "previous_session_id": before.id if before else None,
        "previous_date": before.started_at.date().isoformat() if before else None,
        "changes": [],
        "worsened_elements": [],
        "registration": None,
    }
    if before is None:
        return out
    place(db, files, before)
    out["registration"] = place_session(db, files, s, before)
    rows = db.execute(
        select(Defect.id, Defect.number).where(Defect.session_id.in_([s.id, before.id]))
    ).all()
    numbers = {int(i): n for i, n in rows}
    changes = match_visits(visit_defects(db, before), visit_defects(db, s))
    out["changes"] = [_record(c, numbers) for c in changes]
    structure = db.get(Structure, s.structure_id)
    assert structure is not None
    now, _ = element_condition(db, structure, s)
    then = {c.element.id: c for c in element_condition(db, structure, before)[0]}
    for c in now:
        old = then.get(c.element.id)
        if old is not None and _worse(old.states, c.states):
            out["worsened_elements"].append(
                {
                    "element_id": c.element.id,
                    "number": c.element.number,
                    "before": old.as_dict()["cs"],
                    "after": c.as_dict()["cs"],
                }
            )
    return out


def _worse(before: dict[int, float], after: dict[int, float]) -> bool:
    """Whether more of the element is in CS3 or worse, or in CS4, than before."""
    eps = 1e-6
    return (after[3] + after[4] > before[3] + before[4] + eps) or after[4] > before[4] + eps
