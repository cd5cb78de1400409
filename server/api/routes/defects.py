"""A session's defects: list with filters, read, review, thumbnail."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response
from sqlalchemy import func, select

from server.api.deps import OperatorUser, SessionDep, StateDep, get_current_user
from server.api.queries import (
    DEFECT_SORT_KEYS,
    MAX_INT,
    DefectId,
    count_query,
    defects_query,
    get_defect_or_404,
    get_session_or_404,
)
from server.api.schemas import (
    ConditionState,
    DefectCreate,
    DefectPublic,
    DefectReview,
    DefectsPublic,
    ReviewStatus,
)
from server.errors import Conflict
from server.reports.sightings import defect_sightings
from server.storage.models import Defect, utcnow
from server.storage.thumbnails import defect_image, encode_jpeg

router = APIRouter(
    prefix="/api/sessions", tags=["defects"], dependencies=[Depends(get_current_user)]
)
DEFECT_SORT = "^-?(" + "|".join(DEFECT_SORT_KEYS) + ")$"


@router.get("/{session_id}/defects", response_model=DefectsPublic)
def read_defects(
    db: SessionDep,
    session_id: str,
    defect_class: str | None = None,
    source: Annotated[str | None, Query(pattern="^(mosaic|frame)$")] = None,
    review_status: ReviewStatus | None = None,
    condition_state: ConditionState | None = None,
    below_confidence: Annotated[
        float | None,
        Query(ge=0, le=1, description="only defects the detector is less sure of than this"),
    ] = None,
    sort: Annotated[
        str, Query(pattern=DEFECT_SORT, description="a column, '-' before it for descending")
    ] = "id",
    skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0,
    limit: Annotated[int, Query(ge=1, le=5000)] = 1000,
) -> DefectsPublic:
    """Defects found in a session, filtered by class, source (mosaic or frame), review
    status, condition state or confidence, sorted by a column."""
    get_session_or_404(db, session_id)
    q = defects_query(
        session_id,
        defect_class=defect_class,
        source=source,
        review_status=review_status,
        condition_state=condition_state,
        below_confidence=below_confidence,
        sort=sort,
    )
    rows = db.scalars(q.offset(skip).limit(limit))
    return DefectsPublic(data=list(rows), count=count_query(db, q))  # type: ignore[arg-type]


@router.get("/{session_id}/defects/{defect_id}", response_model=DefectPublic)
def read_defect(db: SessionDep, session_id: str, defect_id: DefectId) -> Defect:
    """One defect."""
    return get_defect_or_404(db, session_id, defect_id)


@router.patch("/{session_id}/defects/{defect_id}", response_model=DefectPublic)
def review_defect(
    db: SessionDep, session_id: str, defect_id: DefectId, body: DefectReview, user: OperatorUser
) -> Defect:
    """Record an inspector's review of a defect: confirm or reject, condition state CS1–CS4,
    AASHTO defect code, comment (operator role). Who and when is kept for the report."""
    defect = get_defect_or_404(db, session_id, defect_id)
    if body.review_status is not None:
        defect.review_status = body.review_status
    if body.condition_state is not None:
        defect.condition_state = body.condition_state
    elif body.clear_condition_state:
        defect.condition_state = None
    if body.comment is not None:
        defect.comment = body.comment
    if body.defect_code is not None:
        defect.defect_code = body.defect_code or None  # 0: back to the class's code
    reset = (
        defect.review_status == "unreviewed"
        and defect.condition_state is None
        and not defect.comment
    )
    # a review taken back entirely names nobody; any other change names who made it
    defect.reviewed_by, defect.reviewed_at = (None, None) if reset else (user.name, utcnow())
    db.commit()
    return defect


@router.get("/{session_id}/defects/{defect_id}/thumbnail.jpg", response_class=Response)
async def read_defect_thumbnail(
    db: SessionDep,
    state: StateDep,
    session_id: str,
    defect_id: DefectId,
    size: Annotated[int, Query(ge=32, le=1024)] = 256,
) -> Response:
    """The defect's neighbourhood (from its frame or the mosaic) with its box drawn, as JPEG."""
    defect = get_defect_or_404(db, session_id, defect_id)
    image = await run_in_threadpool(defect_image, db, state.files, defect, size)
    return Response(
        encode_jpeg(image),
        media_type="image/jpeg",
        headers={"Cache-Control": "private, max-age=60"},
    )


@router.get("/{session_id}/defects/{defect_id}/sightings")
def read_defect_sightings(
    db: SessionDep, session_id: str, defect_id: DefectId
) -> list[dict[str, Any]]:
    """The camera frames the defect was seen in, oldest first: each with its time (robot
    clock, and seconds since the session's first frame), the robot's pose, the telemetry
    sample nearest that moment and the URL of its image."""
    return defect_sightings(db, get_defect_or_404(db, session_id, defect_id))


@router.post(
    "/{session_id}/defects", response_model=DefectPublic, status_code=status.HTTP_201_CREATED
)
def create_defect(
    db: SessionDep, state: StateDep, session_id: str, body: DefectCreate, user: OperatorUser
) -> Defect:
    """Add a defect the detector missed, drawn as a box on the mosaic (operator role). It is
    confirmed and named as drawn by the caller, placed on the structure through the
    mosaic's scale, numbered after the session's others, and kept when detection runs
    again. Its length is the box's longer side; its width is not measured."""
    get_session_or_404(db, session_id)
    try:
        world = json.loads((state.files.results_dir(session_id) / "mosaic.json").read_text())
    except (OSError, ValueError):
        raise Conflict("the session has no mosaic to draw on: run the stitch job first") from None
    if (
        body.bbox_x + body.bbox_w > world["width_px"]
        or body.bbox_y + body.bbox_h > world["height_px"]
    ):
        raise Conflict(f"the box leaves the {world['width_px']}×{world['height_px']} px mosaic")
    ppm, (ox, oy) = float(world["px_per_m"]), world["origin_m"]
    referenced = bool(world.get("world_referenced"))
    long_px = float(max(body.bbox_w, body.bbox_h))
    last = db.scalar(
        select(func.max(Defect.number)).where(
            Defect.session_id == session_id, Defect.source == "mosaic"
        )
    )
    now = utcnow()
    defect = Defect(
        session_id=session_id,
        source="mosaic",
        number=(last or 0) + 1,
        defect_class=body.defect_class,
        bbox_x=body.bbox_x,
        bbox_y=body.bbox_y,
        bbox_w=body.bbox_w,
        bbox_h=body.bbox_h,
        area_px=body.bbox_w * body.bbox_h,
        length_px=long_px,
        max_width_px=0.0,
        mean_width_px=0.0,
        orientation_deg=0.0 if body.bbox_w >= body.bbox_h else 90.0,
        length_mm=long_px / ppm * 1000 if referenced else None,
        area_mm2=body.bbox_w * body.bbox_h / ppm**2 * 1e6
        if referenced and body.defect_class == "corrosion"
        else None,
        world_x_m=ox + body.bbox_x / ppm if referenced else None,
        world_y_m=oy + body.bbox_y / ppm if referenced else None,
        world_w_m=body.bbox_w / ppm if referenced else None,
        world_h_m=body.bbox_h / ppm if referenced else None,
        review_status="confirmed",
        condition_state=body.condition_state,
        comment=body.comment,
        reviewed_by=user.name,
        reviewed_at=now,
        drawn_by=user.name,
    )
    db.add(defect)
    db.commit()
    return defect
