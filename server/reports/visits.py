"""What changed on a structure since its previous inspection: each defect of this session
matched to the previous session's by position in the structure's frame
(:mod:`processing.history.visits`), and the elements whose condition worsened."""

from __future__ import annotations

from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from processing.history.visits import DefectChange, VisitDefect, match_visits
from server.reports.condition import element_condition, structure_box
from server.storage.models import Defect, InspectionSession, Structure


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


def _visit_defects(db: Session, s: InspectionSession) -> list[VisitDefect]:
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


def _record(c: DefectChange, numbers: dict[int, int | None]) -> dict[str, Any]:
    def side(v: VisitDefect | None) -> dict[str, Any] | None:
        if v is None:
            return None
        return {
            "defect_id": v.id,
            "number": numbers.get(v.id),
            "box_m": [round(x, 4) for x in v.box],
            "length_mm": v.length_mm,
            "width_mm": v.width_mm,
            "area_mm2": v.area_mm2,
        }

    kind = c.after or c.before
    assert kind is not None
    return {
        "status": c.status,
        "class": kind.defect_class,
        "before": side(c.before),
        "after": side(c.after),
        "length_change_mm": c.delta("length_mm"),
        "width_change_mm": c.delta("width_mm"),
        "area_change_mm2": c.delta("area_mm2"),
    }


def visit_changes(db: Session, s: InspectionSession) -> dict[str, Any]:
    """The changes since the structure's previous session (none when there is none)."""
    before = previous_session(db, s)
    out: dict[str, Any] = {
        "session_id": s.id,
        "structure_id": s.structure_id,
        "previous_session_id": before.id if before else None,
        "previous_date": before.started_at.date().isoformat() if before else None,
        "changes": [],
        "worsened_elements": [],
    }
    if before is None:
        return out
    rows = db.execute(
        select(Defect.id, Defect.number).where(Defect.session_id.in_([s.id, before.id]))
    ).all()
    numbers = {int(i): n for i, n in rows}
    changes = match_visits(_visit_defects(db, before), _visit_defects(db, s))
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
