"""A session's timeline: its moments (one per camera frame) with the robot's pose, the
camera's footprint and the defects first seen at each, for scrubbing every view together."""

from __future__ import annotations

from functools import partial
from typing import Any

from fastapi import APIRouter, Depends
from starlette.concurrency import run_in_threadpool

from server.api.deps import SessionDep, StateDep, get_current_user
from server.api.queries import get_session_or_404
from server.reports.timeline import session_timeline

router = APIRouter(
    prefix="/api/sessions", tags=["timeline"], dependencies=[Depends(get_current_user)]
)


@router.get("/{session_id}/timeline")
async def read_timeline(db: SessionDep, state: StateDep, session_id: str) -> dict[str, Any]:
    """Every frame of the session as a moment: ``t_s`` (seconds since the session's first
    record, robot clock), the robot's pose ``robot`` (x, y m; yaw rad) and the camera's
    ``footprint`` (4 world corners, m), placed by the best registration there is
    (``placed_by``: mosaic, live map or odometry; the coverage map places frames the same
    way); each defect with the frame it was first seen in (``first_seq``, ``t_s``); the
    numeric telemetry fields with their units (``telemetry.fields``, for
    ``GET /api/sessions/{id}/telemetry/series``)."""
    get_session_or_404(db, session_id)
    live = state.live_map.corrections.get(session_id) if state.live_map is not None else None
    return await run_in_threadpool(
        partial(session_timeline, corrections=live), db, state.files, session_id
    )
