"""A structure's history: its visits oldest first, each defect's history across them, and
a session's mosaic cut to a rectangle of the structure (the same ground on every visit)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query
from fastapi.responses import Response
from pydantic import BaseModel, Field, model_validator

from server.api.deps import SessionDep, StateDep, get_current_user
from server.api.queries import MAX_INT, get_session_or_404, get_structure_or_404
from server.errors import Conflict, NotFound
from server.reports.history import defect_history, stitch_result, visit_summaries
from server.reports.mosaic_crop import crop_mosaic, encode_png
from server.reports.visits import place

router = APIRouter(
    prefix="/api", tags=["structure history"], dependencies=[Depends(get_current_user)]
)

StructureId = Annotated[int, Path(ge=1, le=MAX_INT)]
Metres = Annotated[float, Field(ge=-1e6, le=1e6)]
MIN_CROP_SIDE_M, MAX_CROP_SIDE_M = 0.001, 1000.0


class CropBox(BaseModel):
    """A rectangle in the structure's frame (m), and the crop's size along its longer side."""

    x0: Metres
    y0: Metres
    x1: Metres
    y1: Metres
    size: int = Field(default=384, ge=16, le=1024)

    @model_validator(mode="after")
    def _ordered(self) -> CropBox:
        if not (self.x0 < self.x1 and self.y0 < self.y1):
            raise ValueError("the box needs x0 < x1 and y0 < y1 (metres)")
        if not MIN_CROP_SIDE_M <= max(self.x1 - self.x0, self.y1 - self.y0) <= MAX_CROP_SIDE_M:
            raise ValueError(
                f"the box's longer side must be {MIN_CROP_SIDE_M:g} to {MAX_CROP_SIDE_M:g} m"
            )
        return self


@router.get("/structures/{structure_id}/visits")
def read_visits(db: SessionDep, state: StateDep, structure_id: StructureId) -> list[dict[str, Any]]:
    """The structure's visits, oldest first: session, date, operator, status, defects on the
    structure (mosaic defects not rejected), whether it has a mosaic, and its datum."""
    return visit_summaries(db, state.files, get_structure_or_404(db, structure_id))


@router.get("/structures/{structure_id}/history")
def read_history(db: SessionDep, state: StateDep, structure_id: StructureId) -> dict[str, Any]:
    """Each defect's history across the structure's visits: tracks of entries (visit, date,
    defect, status baseline/new/grown/unchanged/gone, length, width, area, box), each
    visit's defects matched to the visit before it's."""
    return defect_history(db, state.files, get_structure_or_404(db, structure_id))


@router.get("/sessions/{session_id}/mosaic/crop", response_class=Response)
def read_mosaic_crop(
    db: SessionDep, state: StateDep, session_id: str, box: Annotated[CropBox, Query()]
) -> Response:
    """The session's mosaic over a rectangle of its structure (x0, y0, x1, y1 in metres,
    placed through the session's datum), ``size`` px along its longer side, as PNG:
    transparent where the mosaic does not reach."""
    s = get_session_or_404(db, session_id)
    stitch = stitch_result(db, s.id)
    if stitch is None:
        raise Conflict(f"session {session_id} has no mosaic: run the stitch job first")
    if s.structure_id is not None:
        place(db, state.files, s)
    results = state.files.results_dir(s.id)
    try:
        image = crop_mosaic(results, stitch, s.datum, (box.x0, box.y0, box.x1, box.y1), box.size)
    except (OSError, ValueError) as exc:
        raise NotFound(f"cannot read the mosaic of session {session_id}: {exc}") from None
    return Response(
        encode_png(image), media_type="image/png", headers={"Cache-Control": "private, max-age=60"}
    )
