"""A session's coverage: what the camera imaged well enough, and the holes."""

from __future__ import annotations

from functools import partial
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query
from sqlalchemy import func, select
from starlette.concurrency import run_in_threadpool

from processing.coverage import CoverageParams
from server.api.deps import SessionDep, StateDep, get_current_user
from server.api.queries import get_session_or_404
from server.reports.coverage import session_coverage
from server.storage.models import Cloud, Frame

MEMO_SESSIONS = 16  # sessions whose last coverage is kept

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
    sharp and exposed, against the surface in view (the hull of all frame footprints less
    what the ToF clouds show is no surface, such as past the plate's edges): each
    frame's footprint and whether it counts (else why not), the areas, and the holes with
    their positions (metres, world frame), largest first. Live sessions grow as frames
    arrive, placed by odometry refined by the live 3D map's registration while it runs."""
    get_session_or_404(db, session_id)
    params = CoverageParams(required_mm_per_px=state.settings.coverage_mm_per_px)
    live = state.live_map.corrections.get(session_id) if state.live_map is not None else None
    # the answer changes only with new frames or clouds, a new mosaic or a new live registration:
    # pages that ask every second or two for a quiet session get the last one
    frames = db.execute(
        select(func.count(), func.max(Frame.seq)).where(Frame.session_id == session_id)
    ).one()
    clouds = db.execute(
        select(func.count(), func.max(Cloud.seq)).where(Cloud.session_id == session_id)
    ).one()
    mosaic = state.files.results_dir(session_id) / "mosaic.json"
    key = (
        tuple(frames),
        tuple(clouds),
        mosaic.stat().st_mtime_ns if mosaic.is_file() else 0,
        hash(live.tobytes()) if live is not None else 0,
        grid,
        params,
    )
    memo = state.coverage_memo.get(session_id)
    if memo is not None and memo[0] == key:
        return memo[1]
    result = await run_in_threadpool(
        partial(session_coverage, with_grid=grid, corrections=live, surface_cache=state.surface),
        db,
        state.files,
        state.quality,
        session_id,
        params,
    )
    state.coverage_memo[session_id] = (key, result)
    while len(state.coverage_memo) > MEMO_SESSIONS:
        state.coverage_memo.pop(next(iter(state.coverage_memo)))
    return result
