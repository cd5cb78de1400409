"""Structures, their AASHTO elements, which structure a session inspects, and the
element-level condition table (JSON and the BrM CSV layout)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query, status
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field, field_validator
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError

from processing.history.condition import defect_names, element_types
from server.api.deps import OperatorUser, SessionDep, StateDep, get_current_user
from server.api.queries import MAX_INT, get_session_or_404, get_structure_or_404
from server.errors import Conflict, NotFound
from server.reports.condition import condition_csv, element_condition, latest_session
from server.reports.visits import place, visit_changes
from server.storage.models import Element, InspectionSession, Structure, utcnow

router = APIRouter(prefix="/api", tags=["structures"], dependencies=[Depends(get_current_user)])

Name = Annotated[str, Field(min_length=1, max_length=200)]
StructureId = Annotated[int, Path(ge=1, le=MAX_INT)]
ElementId = Annotated[int, Path(ge=1, le=MAX_INT)]


class StructureCreate(BaseModel):
    """A structure an inspection team visits: its name, the owner's id for it (e.g. the
    NBI structure number) and where it is."""

    model_config = ConfigDict(extra="forbid")
    name: Name
    owner_id: str = Field(default="", max_length=100)
    location: str = Field(default="", max_length=2000)


class StructurePublic(StructureCreate):
    id: int
    created_at: datetime
    sessions: int = 0


class ElementCreate(BaseModel):
    """An AASHTO element of the structure: its number, quantity (in the element's unit: m,
    m² or each) and its extent, a rectangle [x0, y0, x1, y1] in the structure's frame (m)."""

    model_config = ConfigDict(extra="forbid")
    number: int
    name: str = Field(default="", max_length=200)
    quantity: float = Field(gt=0, le=1e7)
    box: tuple[float, float, float, float]

    @field_validator("number")
    @classmethod
    def _known(cls, v: int) -> int:
        if v not in element_types():
            raise ValueError(f"element {v} is not an AASHTO steel element (GET /api/aashto)")
        return v

    @field_validator("box")
    @classmethod
    def _ordered(cls, v: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        if not (v[0] < v[2] and v[1] < v[3]) or any(abs(c) > 1e6 for c in v):
            raise ValueError("box must be [x0, y0, x1, y1] with x0 < x1 and y0 < y1 (metres)")
        return v


class ElementPublic(ElementCreate):
    id: int
    structure_id: int
    unit: str


class SessionStructure(BaseModel):
    """The structure a session inspects, and its datum: the pose (x, y in metres, yaw in
    radians) of the session's world frame in the structure's (the robot's start on the
    structure's marked datum)."""

    model_config = ConfigDict(extra="forbid")
    structure_id: int | None = Field(ge=1, le=MAX_INT)
    datum: dict[str, float] = Field(default_factory=lambda: {"x": 0.0, "y": 0.0, "yaw": 0.0})

    @field_validator("datum")
    @classmethod
    def _datum(cls, v: dict[str, float]) -> dict[str, float]:
        if set(v) - {"x", "y", "yaw"}:
            raise ValueError("datum has x, y and yaw only")
        return {k: float(v.get(k, 0.0)) for k in ("x", "y", "yaw")}


def _public(db: SessionDep, s: Structure) -> StructurePublic:
    n = db.scalar(select(func.count()).where(InspectionSession.structure_id == s.id)) or 0
    return StructurePublic(
        id=s.id,
        name=s.name,
        owner_id=s.owner_id,
        location=s.location,
        created_at=s.created_at,
        sessions=n,
    )


def _element_public(e: Element) -> ElementPublic:
    return ElementPublic(
        id=e.id,
        structure_id=e.structure_id,
        number=e.number,
        name=e.name or element_types()[e.number].name,
        quantity=e.quantity,
        box=(e.x0, e.y0, e.x1, e.y1),
        unit=element_types()[e.number].unit,
    )


@router.get("/aashto")
def read_aashto() -> dict[str, Any]:
    """The AASHTO elements and defect codes steelscan knows (steel and its coating)."""
    return {
        "elements": [
            {"number": t.number, "name": t.name, "unit": t.unit, "defects": list(t.defects)}
            for t in element_types().values()
        ],
        "defects": [{"code": c, "name": n} for c, n in defect_names().items()],
    }


@router.get("/structures", response_model=list[StructurePublic])
def read_structures(db: SessionDep) -> list[StructurePublic]:
    """Every structure."""
    return [_public(db, s) for s in db.scalars(select(Structure).order_by(Structure.name))]


@router.post("/structures", response_model=StructurePublic, status_code=status.HTTP_201_CREATED)
def create_structure(db: SessionDep, user: OperatorUser, body: StructureCreate) -> StructurePublic:
    """Add a structure (its name is unique)."""
    s = Structure(**body.model_dump(), created_at=utcnow())
    db.add(s)
    try:
        db.commit()
    except IntegrityError:
        db.rollback()
        raise Conflict(f"a structure named {body.name!r} exists") from None
    return _public(db, s)


@router.get("/structures/{structure_id}", response_model=StructurePublic)
def read_structure(db: SessionDep, structure_id: StructureId) -> StructurePublic:
    """One structure."""
    return _public(db, get_structure_or_404(db, structure_id))


@router.get("/structures/{structure_id}/elements", response_model=list[ElementPublic])
def read_elements(db: SessionDep, structure_id: StructureId) -> list[ElementPublic]:
    """The structure's elements."""
    get_structure_or_404(db, structure_id)
    rows = db.scalars(
        select(Element).where(Element.structure_id == structure_id).order_by(Element.id)
    )
    return [_element_public(e) for e in rows]


@router.post(
    "/structures/{structure_id}/elements",
    response_model=ElementPublic,
    status_code=status.HTTP_201_CREATED,
)
def create_element(
    db: SessionDep, user: OperatorUser, structure_id: StructureId, body: ElementCreate
) -> ElementPublic:
    """Define an element on the structure."""
    get_structure_or_404(db, structure_id)
    x0, y0, x1, y1 = body.box
    e = Element(
        structure_id=structure_id,
        number=body.number,
        name=body.name,
        quantity=body.quantity,
        x0=x0,
        y0=y0,
        x1=x1,
        y1=y1,
        created_at=utcnow(),
    )
    db.add(e)
    db.commit()
    return _element_public(e)


@router.delete("/structures/{structure_id}/elements/{element_id}", status_code=204)
def delete_element(
    db: SessionDep, user: OperatorUser, structure_id: StructureId, element_id: ElementId
) -> Response:
    """Remove an element."""
    e = db.get(Element, element_id)
    if e is None or e.structure_id != structure_id:
        raise NotFound(f"element {element_id} not found on structure {structure_id}")
    db.delete(e)
    db.commit()
    return Response(status_code=204)


@router.put("/sessions/{session_id}/structure", response_model=SessionStructure)
def set_session_structure(
    db: SessionDep, user: OperatorUser, session_id: str, body: SessionStructure
) -> SessionStructure:
    """Say which structure a session inspects and where its world frame lies on it."""
    s = get_session_or_404(db, session_id)
    if body.structure_id is not None:
        get_structure_or_404(db, body.structure_id)
    s.structure_id = body.structure_id
    s.datum = body.datum
    db.commit()
    return body


@router.get("/sessions/{session_id}/changes")
def read_changes(db: SessionDep, state: StateDep, session_id: str) -> dict[str, Any]:
    """What changed since the structure's previous inspection: the session registered to
    it (its mosaic to the previous one's), each defect new, grown, unchanged or gone, with
    its length, width and area change, and the elements whose condition worsened."""
    return visit_changes(db, state.files, get_session_or_404(db, session_id))


@router.get("/structures/{structure_id}/condition")
def read_condition(
    db: SessionDep,
    state: StateDep,
    structure_id: StructureId,
    session_id: Annotated[str | None, Query(max_length=36)] = None,
) -> dict[str, Any]:
    """Each element's quantity in CS1-CS4 from a session's defects (the structure's latest
    session unless ``session_id``), and the defects on no element."""
    structure = get_structure_or_404(db, structure_id)
    session = _session_of(db, structure, session_id)
    if session is not None:
        place(db, state.files, session)
    table, unplaced = element_condition(db, structure, session)
    return {
        "structure_id": structure.id,
        "structure": structure.name,
        "session_id": session.id if session else None,
        "elements": [c.as_dict() for c in table],
        "unplaced_defects": unplaced,
    }


@router.get("/structures/{structure_id}/condition.csv")
def read_condition_csv(
    db: SessionDep,
    state: StateDep,
    structure_id: StructureId,
    session_id: Annotated[str | None, Query(max_length=36)] = None,
) -> Response:
    """The condition table as CSV: element rows and element/defect rows with CS quantities."""
    structure = get_structure_or_404(db, structure_id)
    session = _session_of(db, structure, session_id)
    if session is not None:
        place(db, state.files, session)
    table, _ = element_condition(db, structure, session)
    return Response(
        condition_csv(structure, table),
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="condition-{structure.id}.csv"'},
    )


def _session_of(
    db: SessionDep, structure: Structure, session_id: str | None
) -> InspectionSession | None:
    if session_id is None:
        return latest_session(db, structure.id)
    session = get_session_or_404(db, session_id)
    if session.structure_id != structure.id:
        raise NotFound(f"session {session_id} does not inspect structure {structure.id}")
    return session
