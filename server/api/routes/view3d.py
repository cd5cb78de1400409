"""The 3D views through the ground station: ``/viser/live/`` (also ``/viser/``) proxies the
loopback-only viser server of the live robots, ``/viser/session/{id}/`` the one of a finished
session (HTTP and websocket, for authenticated users); ``POST /api/sessions/{id}/view3d``
loads a session's map, trajectory and defects into its own view.

A browser embeds the view in an iframe, which cannot send an Authorization header: it
opens ``/viser/?token=...`` once, and the proxy answers with an HttpOnly, SameSite=Strict
cookie scoped to ``/viser`` that the page's own requests and websocket then carry.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import anyio
import httpx
import numpy as np
from fastapi import APIRouter, Depends, Request, WebSocket
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import select
from websockets.asyncio.client import connect

from server.api.accounts import accounts_exist, user_for_token
from server.api.deps import SessionDep, StateDep, get_current_user, same_origin
from server.api.queries import get_session_or_404
from server.api.wsproxy import offered_subprotocols, pass_through
from server.errors import NotFound
from server.live.events import DefectSelected
from server.live.scene3d import DefectMarker, Scene3D
from server.live.scenes import Scenes
from server.reports.fields import POSITION_MEANING
from server.state import AppState
from server.storage.models import Defect, InspectionSession

log = logging.getLogger(__name__)
router = APIRouter(tags=["3d view"])
COOKIE = "steelscan_view"


def _allowed(state: AppState, token: str | None) -> bool:
    with state.factory() as db:
        return not accounts_exist(db) or user_for_token(db, token) is not None


def _scenes_or_404(state: AppState) -> Scenes:
    if state.scenes is None:
        raise NotFound("the 3D view is switched off (STEELSCAN_VIEW3D=false)")
    return state.scenes


def _view_or_404(state: AppState, key: str) -> Scene3D:
    scene = _scenes_or_404(state).get(key)
    if scene is None:
        raise NotFound(f"no 3D view of session {key} is open: POST /api/sessions/{key}/view3d")
    return scene


@router.get("/viser/", include_in_schema=False)
@router.get("/viser/live/", include_in_schema=False)
async def read_live_view(request: Request, state: StateDep) -> Response:
    """The live robots' 3D view."""
    return await _page(request, state, _view_or_404(state, "live"))


@router.get("/viser/session/{session_id}/", include_in_schema=False)
async def read_session_view(request: Request, state: StateDep, session_id: str) -> Response:
    """A session's own 3D view."""
    return await _page(request, state, _view_or_404(state, session_id))


async def _page(request: Request, state: AppState, scene: Scene3D) -> Response:
    """The viser page, for a user with a valid token (query, once) or view cookie."""
    query_token = request.query_params.get("token")
    token = query_token or request.cookies.get(COOKIE)
    if not await anyio.to_thread.run_sync(_allowed, state, token):
        return Response(
            "a valid token is required: open /viser/?token=<bearer token>",
            status_code=401,
            media_type="text/plain",
        )
    async with httpx.AsyncClient(timeout=30) as client:
        upstream = await client.get(
            f"http://127.0.0.1:{scene.port}/", headers={"Accept-Encoding": "identity"}
        )
    response = Response(
        upstream.content,
        status_code=upstream.status_code,
        media_type=upstream.headers.get("content-type"),
    )
    if query_token:
        response.set_cookie(COOKIE, query_token, httponly=True, samesite="strict", path="/viser")
    return response


@router.websocket("/viser")  # the viser client drops the trailing slash
@router.websocket("/viser/")
@router.websocket("/viser/live")
async def live_view_socket(websocket: WebSocket) -> None:
    """The live view's websocket."""
    await _socket(websocket, "live")


@router.websocket("/viser/session/{session_id}")
async def session_view_socket(websocket: WebSocket, session_id: str) -> None:
    """A session view's websocket."""
    await _socket(websocket, session_id)


async def _socket(websocket: WebSocket, key: str) -> None:
    """The viser websocket, passed through to the loopback server for authenticated users."""
    state: AppState = websocket.app.state.steelscan
    scene = state.scenes.get(key) if state.scenes is not None else None
    if scene is None:
        await websocket.close(code=1008, reason="no such 3D view")
        return
    if not same_origin(websocket, state.settings.allowed_origins):
        await websocket.close(code=1008, reason="cross-site websocket refused")
        return
    token = websocket.query_params.get("token") or websocket.cookies.get(COOKIE)
    if not await anyio.to_thread.run_sync(_allowed, state, token):
        await websocket.close(code=1008, reason="a valid token is required")
        return
    protocols = offered_subprotocols(websocket)
    async with connect(
        f"ws://127.0.0.1:{scene.port}/",
        subprotocols=protocols or None,  # type: ignore[arg-type]
        max_size=None,
        compression=None,
    ) as upstream:
        await websocket.accept(subprotocol=upstream.subprotocol)
        await pass_through(websocket, upstream)


def defect_marker(d: Defect) -> DefectMarker:
    """A placed defect's marker: a sphere at the middle of its box on the structure, and the
    text the view shows for it, whose position is the defect's one position everywhere
    (``world_x_m``, ``world_y_m``: the box's corner nearest the origin) and then the box."""
    x0, y0 = float(d.world_x_m or 0.0), float(d.world_y_m or 0.0)
    w, h = float(d.world_w_m or 0.0), float(d.world_h_m or 0.0)
    text = (
        f"**Defect {d.number or d.id}** — {d.defect_class}  \n"
        f"length {d.length_mm or 0:.1f} mm, max width {d.max_width_mm or 0:.2f} mm  \n"
        f"at x {x0:.3f} m, y {y0:.3f} m ({POSITION_MEANING})  \n"
        f"box x {x0:.3f}–{x0 + w:.3f} m, y {y0:.3f}–{y0 + h:.3f} m ({d.source})"
    )
    return DefectMarker(
        d.id, d.number or d.id, d.defect_class, x0 + w / 2, y0 + h / 2, max(w, h), text
    )


def session_scene(db: Any, state: AppState, session_id: str) -> dict[str, Any]:
    """Load a session's map, trajectory and defects into the 3D view; what was shown."""
    import open3d as o3d

    from processing.poses import parse_tum

    s = db.get(InspectionSession, session_id)
    results = state.files.results_dir(session_id)
    points = None
    if (results / "map.ply").is_file():
        points = np.asarray(o3d.io.read_point_cloud(str(results / "map.ply")).points)
    trajectory = None
    if (results / "trajectory.tum").is_file():
        _, poses = parse_tum((results / "trajectory.tum").read_text())
        trajectory = poses[:, :3, 3] if len(poses) else None
    rows = db.scalars(
        select(Defect).where(Defect.session_id == session_id, Defect.world_x_m.is_not(None))
    )
    rows = list(rows)
    mosaic_rows = [d for d in rows if d.source == "mosaic"]
    markers = [defect_marker(d) for d in mosaic_rows or rows]
    title = f"{s.structure or 'session'} — {session_id[:8]}" if s is not None else session_id
    scenes = _scenes_or_404(state)
    scenes.for_session(session_id).show_session(session_id, points, trajectory, markers, title)
    return {
        "session_id": session_id,
        "points": 0 if points is None else len(points),
        "trajectory_poses": 0 if trajectory is None else len(trajectory),
        "defects": len(markers),
        "url": f"/viser/session/{session_id}/",
    }


@router.post("/api/sessions/{session_id}/view3d", dependencies=[Depends(get_current_user)])
async def show_in_3d(db: SessionDep, state: StateDep, session_id: str) -> dict[str, Any]:
    """Open this session's own 3D view (at the returned ``url``): its map coloured by height,
    its trajectory and a numbered marker per defect placed on the structure. Clicking a
    marker selects the defect on the dashboard (a ``defect_selected`` event on the live
    websocket). Live robots have their own view (``/viser/live/``); neither changes the
    other."""
    scenes = _scenes_or_404(state)
    get_session_or_404(db, session_id)
    shown = await anyio.to_thread.run_sync(session_scene, db, state, session_id)
    loop = asyncio.get_running_loop()
    scene = scenes.get(session_id)

    def selected(defect_id: int) -> None:  # in viser's thread: hand over to the event loop
        event = DefectSelected(session_id=session_id, defect_id=defect_id)
        loop.call_soon_threadsafe(state.hub.publish, event)

    if scene is not None:
        scene.on_select = selected
    return shown


@router.post(
    "/api/sessions/{session_id}/view3d/focus/{defect_id}",
    dependencies=[Depends(get_current_user)],
)
def focus_in_3d(state: StateDep, session_id: str, defect_id: int) -> dict[str, Any]:
    """Fly the session's 3D view to a defect's marker (the dashboard does this when a defect
    is selected anywhere else)."""
    scene = _view_or_404(state, session_id)
    if not scene.focus(defect_id):
        raise NotFound(f"defect {defect_id} has no marker in the 3D view of {session_id}")
    return {"session_id": session_id, "defect_id": defect_id}


class Moment(BaseModel):
    """The robot's pose at one moment of the session (world metres and radians, as
    ``GET /api/sessions/{id}/timeline`` gives it) and the moment's words for the panel."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    x: float = Field(ge=-1e4, le=1e4)
    y: float = Field(ge=-1e4, le=1e4)
    yaw: float = Field(ge=-100.0, le=100.0)
    label: str = Field(default="", max_length=200)


@router.post(
    "/api/sessions/{session_id}/view3d/moment",
    dependencies=[Depends(get_current_user)],
)
def moment_in_3d(state: StateDep, session_id: str, moment: Moment) -> dict[str, Any]:
    """Put the robot where it was at one moment in the session's 3D view (the dashboard's
    timeline does this as a reviewer scrubs it)."""
    scene = _view_or_404(state, session_id)
    scene.show_moment(moment.x, moment.y, moment.yaw, moment.label)
    return {"session_id": session_id, **moment.model_dump()}
