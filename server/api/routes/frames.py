"""A session's camera frames: the list and each frame's JPEG."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query
from fastapi.responses import Response
from sqlalchemy import select

from server.api.deps import SessionDep, StateDep, get_current_user
from server.api.queries import (
    MAX_INT,
    Seq,
    count_rows,
    get_frame_or_404,
    get_session_or_404,
    read_payload,
)
from server.api.schemas import FramesPublic
from server.storage.models import Frame

router = APIRouter(
    prefix="/api/sessions", tags=["frames"], dependencies=[Depends(get_current_user)]
)


@router.get("/{session_id}/frames", response_model=FramesPublic)
def read_frames(
    db: SessionDep,
    session_id: str,
    skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> FramesPublic:
    """Camera frames of a session in sequence order."""
    get_session_or_404(db, session_id)
    rows = db.scalars(
        select(Frame)
        .where(Frame.session_id == session_id)
        .order_by(Frame.seq)
        .offset(skip)
        .limit(limit)
    )
    return FramesPublic(data=list(rows), count=count_rows(db, Frame, session_id))  # type: ignore[arg-type]


@router.get("/{session_id}/frames/{seq}/image", response_class=Response)
def read_frame_image(db: SessionDep, state: StateDep, session_id: str, seq: Seq) -> Response:
    """The JPEG of one frame."""
    frame = get_frame_or_404(db, session_id, seq)
    return Response(
        read_payload(state.files, frame, f"frame {seq} of session {session_id}"),
        media_type="image/jpeg",
        headers={"Cache-Control": "private, max-age=3600"},
    )
