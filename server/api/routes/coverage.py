"""A session's coverage: what the camera imaged well enough, and the holes."""

from __future__ import annotations

from functools import partial
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query
from starlette.concurrency import run_in_threadpool

from processing.coverage import CoverageParams
from server.api.deps import SessionDep, StateDep, get_current_user
from server.api.queries import get_session_or_404
from server.reports.coverage import session_coverage

router = APIRouter(
    prefix="/api/sessions", tags=["coverage"], dependencies=[Depends(get_current_user)]
)


@router.get("/{session_id}/coverage")
async def read_coverage(
    db: SessionDep,
    state: StateDep,
    session_id: str,
    grid: Annotated[bool, Query(description="include the hole grid for drawing")] = True,
) -> dict[str, Any]:
    """The surface the camera imaged at the required resolution (``STEELSCAN_COVERAGE_MM_PER_PX``),
    sharp and exposed, against the surface in view (the hull of all frame footprints): each
    frame's footprint and whether it counts (else why not), the areas, and the holes with
    their positions (metres, world frame), largest first. Live sessions grow as frames
    arrive, placed by odometry refined by the live 3D map's registration while it runs."""
    get_session_or_404(db, session_id)
    params = CoverageParams(required_mm_per_px=state.settings.coverage_mm_per_px)
    live = state.live_map.corrections.get(session_id) if state.live_map is not None else None
    return await run_in_threadpool(
        partial(session_coverage, with_grid=grid, corrections=live),
        db,
        state.files,
        state.quality,
        session_id,
        params,
    )
