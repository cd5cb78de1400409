"""A session's processing results: mosaic, map, trajectory, masks, Deep Zoom tiles."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Path
from fastapi.responses import FileResponse

from server.api.deps import SessionDep, StateDep, get_current_user
from server.api.queries import MAX_INT, get_session_or_404
from server.errors import NotFound

router = APIRouter(
    prefix="/api/sessions", tags=["results"], dependencies=[Depends(get_current_user)]
)
RESULT_FILES = {
    "mosaic.png": "image/png",
    "mosaic_overview.png": "image/png",
    "mosaic_coverage.png": "image/png",
    "mosaic.json": "application/json",
    "mosaic.dzi": "application/xml",
    "map.ply": "application/octet-stream",
    "trajectory.tum": "text/plain",
    "crack_mask.png": "image/png",
    "corrosion_mask.png": "image/png",
}


@router.get("/{session_id}/results/{name}", response_class=FileResponse)
def read_result_file(db: SessionDep, state: StateDep, session_id: str, name: str) -> FileResponse:
    """A processing result file (mosaic.png, mosaic_overview.png, map.ply, trajectory.tum, masks)."""
    get_session_or_404(db, session_id)
    if name not in RESULT_FILES:
        raise NotFound(f"no result file named {name!r}; known: {sorted(RESULT_FILES)}")
    path = state.files.results_dir(session_id) / name
    if not path.is_file():
        raise NotFound(f"{name} of session {session_id} does not exist yet")
    return FileResponse(path, media_type=RESULT_FILES[name], filename=name)


@router.get("/{session_id}/mosaic_files/{level}/{col}_{row}.jpg", response_class=FileResponse)
def read_mosaic_tile(
    db: SessionDep,
    state: StateDep,
    session_id: str,
    level: Annotated[int, Path(ge=0, le=64)],
    col: Annotated[int, Path(ge=0, le=MAX_INT)],
    row: Annotated[int, Path(ge=0, le=MAX_INT)],
) -> FileResponse:
    """One tile of the mosaic's Deep Zoom pyramid (``results/mosaic.dzi`` describes it)."""
    get_session_or_404(db, session_id)
    path = state.files.results_dir(session_id) / "mosaic_files" / str(level) / f"{col}_{row}.jpg"
    if not path.is_file():
        raise NotFound(f"no tile {level}/{col}_{row} in the mosaic of session {session_id}")
    return FileResponse(
        path, media_type="image/jpeg", headers={"Cache-Control": "private, max-age=3600"}
    )
