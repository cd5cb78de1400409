"""A structure's element-level condition (AASHTO Manual for Bridge Element Inspection) from
one of its inspection sessions: each defect placed on its element by its position in the
structure's frame, coded, and each element's quantity in CS1-CS4
(:mod:`processing.history.condition`); as JSON and as the element/defect CSV layout of
bridge management systems (AASHTOWare BrM)."""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from processing.history.condition import (
    CodedDefect,
    Element,
    code_of,
    defect_names,
    element_of,
    element_types,
    state_of,
    state_quantities,
)
from processing.poses import se2_matrix
from server.storage.models import Defect, InspectionSession, Structure
from server.storage.models import Element as ElementRow


def structure_box(
    defect: Defect, datum: dict[str, Any] | None
) -> tuple[float, float, float, float] | None:
    """The defect's world box in the structure's frame (the session's datum: its world
    frame's pose x, y, yaw in the structure's), axis-aligned; None without a position."""
    if defect.world_x_m is None or defect.world_y_m is None:
        return None
    w, h = defect.world_w_m or 0.0, defect.world_h_m or 0.0
    x, y = defect.world_x_m, defect.world_y_m  # the box's corner nearest the origin
    d = datum or {}
    T = se2_matrix(float(d.get("x", 0.0)), float(d.get("y", 0.0)), float(d.get("yaw", 0.0)))
    corners = np.array([[x, y, 1], [x + w, y, 1], [x + w, y + h, 1], [x, y + h, 1]]) @ T.T
    return (
        float(corners[:, 0].min()),
        float(corners[:, 1].min()),
        float(corners[:, 0].max()),
        float(corners[:, 1].max()),
    )


@dataclass
class ElementCondition:
    """One element's condition."""

    element: ElementRow
    states: dict[int, float]
    defects: list[dict[str, Any]] = field(default_factory=list)
    by_code: dict[int, dict[int, float]] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """The JSON form."""
        kind = element_types().get(self.element.number)
        return {
            "element_id": self.element.id,
            "number": self.element.number,
            "name": self.element.name or (kind.name if kind else ""),
            "unit": kind.unit if kind else "",
            "quantity": self.element.quantity,
            "cs": {f"cs{k}": v for k, v in self.states.items()},
            "defects": self.defects,
            "by_defect": [
                {
                    "code": code,
                    "name": defect_names().get(code, ""),
                    **{f"cs{k}": v for k, v in q.items()},
                }
                for code, q in sorted(self.by_code.items())
            ],
        }


def latest_session(db: Session, structure_id: int) -> InspectionSession | None:
    """The structure's most recent session."""
    return db.scalars(
        select(InspectionSession)
        .where(InspectionSession.structure_id == structure_id)
        .order_by(InspectionSession.started_at.desc())
        .limit(1)
    ).first()


def element_condition(
    db: Session, structure: Structure, session: InspectionSession | None
) -> tuple[list[ElementCondition], list[dict[str, Any]]]:
    """Each element's condition from ``session``'s defects (rejected ones left out), and
    the defects on no element."""
    rows = db.scalars(
        select(ElementRow).where(ElementRow.structure_id == structure.id).order_by(ElementRow.id)
    ).all()
    elements = [
        Element(r.id, r.number, r.quantity, (r.x0, r.y0, r.x1, r.y1))
        for r in rows
        if r.number in element_types()
    ]
    placed: dict[int, list[tuple[CodedDefect, dict[str, Any]]]] = {e.id: [] for e in elements}
    unplaced: list[dict[str, Any]] = []
    defects = (
        []
        if session is None
        else db.scalars(
            select(Defect)
            .where(Defect.session_id == session.id, Defect.source == "mosaic")
            .where(Defect.review_status != "rejected")
            .order_by(Defect.number)
        ).all()
    )
    for d in defects:
        box = structure_box(d, session.datum if session else None)
        coded = CodedDefect(
            d.id,
            box or (0.0, 0.0, 0.0, 0.0),
            code_of(d.defect_class, d.defect_code),
            state_of(d.defect_class, d.condition_state),
        )
        info = {
            "defect_id": d.id,
            "number": d.number,
            "class": d.defect_class,
            "code": coded.code,
            "state": f"CS{coded.state}",
        }
        where = element_of(box, elements) if box else None
        if where is None:
            unplaced.append(info)
        else:
            placed[where].append((coded, info))
    out = []
    known = [r for r in rows if r.number in element_types()]
    for row, e in zip(known, elements, strict=True):
        mine = placed[e.id]
        by_code = {
            code: state_quantities(e, [c for c, _ in mine if c.code == code])
            for code in sorted({c.code for c, _ in mine})
        }
        out.append(
            ElementCondition(
                row, state_quantities(e, [c for c, _ in mine]), [i for _, i in mine], by_code
            )
        )
    return out, unplaced


def condition_csv(structure: Structure, conditions: list[ElementCondition]) -> str:
    """Element and element/defect rows with their CS quantities, as BrM imports them: one
    row per element (its totals), then one per defect code found on it."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        [
            "structure",
            "owner_id",
            "element",
            "element_name",
            "defect",
            "defect_name",
            "unit",
            "total_quantity",
            "cs1",
            "cs2",
            "cs3",
            "cs4",
        ]
    )
    for c in conditions:
        d = c.as_dict()
        w.writerow(
            [
                structure.name,
                structure.owner_id,
                d["number"],
                d["name"],
                "",
                "",
                d["unit"],
                d["quantity"],
                *d["cs"].values(),
            ]
        )
        for code in d["by_defect"]:
            affected = [code["cs2"], code["cs3"], code["cs4"]]
            w.writerow(
                [
                    structure.name,
                    structure.owner_id,
                    d["number"],
                    d["name"],
                    code["code"],
                    code["name"],
                    d["unit"],
                    round(sum(affected), 4),
                    0,
                    *affected,
                ]
            )
    return buf.getvalue()
