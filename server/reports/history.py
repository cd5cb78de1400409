"""A structure's visits and each defect's history across them: the matches of consecutive
visits (:func:`server.reports.visits.visit_changes`) chained into tracks, one per defect,
with its size at each visit."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.reports.visits import place, side_record, visit_changes, visit_defects
from server.storage.files import SessionFiles
from server.storage.models import Defect, InspectionSession, Job, JobState, Structure

SIDE_FIELDS = ("defect_id", "number", "length_mm", "width_mm", "area_mm2", "box_m")


@dataclass(frozen=True)
class Visit:
    """One visit as a track names it."""

    session_id: str
    date: str  # ISO date of its start


def structure_visits(db: Session, structure_id: int) -> list[InspectionSession]:
    """The structure's sessions, oldest first."""
    return list(
        db.scalars(
            select(InspectionSession)
            .where(InspectionSession.structure_id == structure_id)
            .order_by(InspectionSession.started_at, InspectionSession.id)
        )
    )


def _counted(q: Any) -> Any:
    """Defects as the structure counts them: on the mosaic, not rejected in review."""
    return q.where(Defect.source == "mosaic", Defect.review_status != "rejected")


def stitch_result(db: Session, session_id: str) -> dict[str, Any] | None:
    """The result of the session's latest finished stitch job (its mosaic's place in the
    session's world frame: ``origin_m``, ``px_per_m``, ``overview_scale``), or None."""
    job = db.scalars(
        select(Job)
        .where(Job.session_id == session_id, Job.kind == "stitch", Job.state == JobState.done)
        .order_by(Job.id.desc())
        .limit(1)
    ).first()
    if job is None or not job.result.get("overview_path"):
        return None
    return dict(job.result)


def visit_summaries(db: Session, files: SessionFiles, structure: Structure) -> list[dict[str, Any]]:
    """Each visit, oldest first: its session, date, operator, status, defects counted on
    the structure, whether it has a mosaic, and its datum on the structure (each visit
    placed through the one before it first, :func:`server.reports.visits.place`)."""
    visits = structure_visits(db, structure.id)
    if visits:
        place(db, files, visits[-1])
    counts = dict(
        db.execute(
            _counted(
                select(Defect.session_id, func.count()).where(
                    Defect.session_id.in_([s.id for s in visits])
                )
            ).group_by(Defect.session_id)
        ).all()
    )
    out = []
    for s in visits:
        d = s.datum or {}
        out.append(
            {
                "session_id": s.id,
                "started_at": s.started_at.isoformat(),
                "date": s.started_at.date().isoformat(),
                "operator": s.operator,
                "robot": s.robot.name if s.robot else None,
                "status": s.status.value,
                "defects": int(counts.get(s.id, 0)),
                "mosaic": stitch_result(db, s.id) is not None,
                "datum": {k: float(d.get(k, 0.0)) for k in ("x", "y", "yaw")},
            }
        )
    return out


def first_visit_defects(db: Session, s: InspectionSession) -> list[dict[str, Any]]:
    """The visit's defects placed on the structure, as one side of a change."""
    rows = db.execute(select(Defect.id, Defect.number).where(Defect.session_id == s.id)).all()
    numbers = {int(i): n for i, n in rows}
    return [
        {"class": v.defect_class, **side_record(v, numbers.get(v.id))} for v in visit_defects(db, s)
    ]


def _entry(visit: Visit, status: str, side: dict[str, Any] | None) -> dict[str, Any]:
    return {
        "session_id": visit.session_id,
        "date": visit.date,
        "status": status,
        **{k: (side or {}).get(k) for k in SIDE_FIELDS},
    }


def _parts(change: dict[str, Any], side: str) -> list[int]:
    parts = change.get(f"parts_{side}") or []
    own = change[side]["defect_id"] if change.get(side) else None
    return [*parts, own] if own is not None and own not in parts else list(parts)


def chain_tracks(
    visits: Sequence[Visit],
    changes: Sequence[dict[str, Any]],
    first: Sequence[dict[str, Any]] = (),
) -> list[dict[str, Any]]:
    """Each defect's history across ``visits`` (oldest first): ``changes[i]`` is what
    changed from ``visits[i]`` to ``visits[i + 1]`` (the ``changes`` of
    :func:`visit_changes`); ``first``, the first visit's defects where there is no change
    to take them from (one visit only).

    A track is one defect's entries, one per visit from the one it was first seen on:
    ``baseline`` on the first visit, then ``new``, ``grown`` or ``unchanged``, and ``gone``
    last where it is no longer seen. A visit's defect continues the track that one of its
    pieces (the detections of a group, ``parts_before``) was on at the visit before; a
    defect split in two since continues in two tracks with the same past."""
    if len(changes) != max(0, len(visits) - 1):
        raise ValueError(f"changes: {len(changes)} for {len(visits)} visits, expected one fewer")
    if not visits:
        return []
    tracks: list[dict[str, Any]] = []
    at: dict[int, dict[str, Any]] = {}  # defect id -> its track, on the latest visit
    t: dict[str, Any] | None
    if changes:
        seen = [c for c in changes[0]["changes"] if c["before"]]
        first = [{"class": c["class"], **c["before"]} for c in seen]
        pieces = [_parts(c, "before") for c in seen]
    else:
        pieces = [[d["defect_id"]] for d in first]
    for d, ids in zip(first, pieces, strict=True):
        tracks.append({"class": d["class"], "first": 0, "entries": []})
        tracks[-1]["entries"].append(_entry(visits[0], "baseline", d))
        at.update(dict.fromkeys(ids, tracks[-1]))
    for k, (visit, change) in enumerate(zip(visits[1:], changes, strict=True), start=1):
        now: dict[int, dict[str, Any]] = {}
        for c in change["changes"]:
            t = next((at[p] for p in _parts(c, "before") if p in at), None)
            if t is None:  # first seen here, or (unmatched before) on the visit before
                t = {"class": c["class"], "first": k, "entries": []}
                if c["before"]:
                    t["first"] = k - 1
                    t["entries"].append(
                        _entry(visits[k - 1], "baseline" if k == 1 else "new", c["before"])
                    )
                tracks.append(t)
            elif t["entries"][-1]["session_id"] == visit.session_id:  # split since
                t = {**t, "entries": t["entries"][:-1]}
                tracks.append(t)
            t["entries"].append(_entry(visit, c["status"], c["after"]))
            if c["after"]:
                now.update(dict.fromkeys(_parts(c, "after"), t))
        at = now
    tracks.sort(key=lambda t: (t["first"], t["entries"][0]["number"] or 0))
    return [
        {"track_id": i, "class": t["class"], "entries": t["entries"]}
        for i, t in enumerate(tracks, start=1)
    ]


def defect_history(db: Session, files: SessionFiles, structure: Structure) -> dict[str, Any]:
    """The structure's visits and each defect's history across them (:func:`chain_tracks`),
    the matches of each visit with the one before it taken from :func:`visit_changes`
    (one registration per visit, kept once made)."""
    sessions = structure_visits(db, structure.id)
    visits = [Visit(s.id, s.started_at.date().isoformat()) for s in sessions]
    changes = [visit_changes(db, files, s) for s in sessions[1:]]
    first = first_visit_defects(db, sessions[0]) if len(sessions) == 1 else ()
    return {
        "structure_id": structure.id,
        "visits": [{"session_id": v.session_id, "date": v.date} for v in visits],
        "tracks": chain_tracks(visits, changes, first),
    }
