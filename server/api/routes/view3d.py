"""The 3D view through the ground station: ``/viser/`` proxies the loopback-only viser server
(HTTP and websocket) for authenticated users, and ``POST /api/sessions/{id}/view3d`` puts a
session's map, trajectory and defects into it.

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
from fastapi import APIRouter, Depends, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import Response
from sqlalchemy import select
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from server.api.accounts import accounts_exist, user_for_token
from server.api.deps import SessionDep, StateDep, require, same_origin
from server.api.queries import get_session_or_404
from server.errors import NotFound
from server.live.scene3d import DefectMarker
from server.state import AppState
from server.storage.models import Defect, InspectionSession, Role

log = logging.getLogger(__name__)
router = APIRouter(tags=["3d view"])
COOKIE = "steelscan_view"


def _allowed(state: AppState, token: str | None) -> bool:
    with state.factory() as db:
        return not accounts_exist(db) or user_for_token(db, token) is not None


def _scene_or_404(state: AppState) -> Any:
    if state.scene is None:
        raise NotFound("the 3D view is switched off (STEELSCAN_VIEW3D=false)")
    return state.scene


@router.get("/viser/", include_in_schema=False)
async def read_view(request: Request, state: StateDep) -> Response:
    """The viser page, for a user with a valid token (query, once) or view cookie."""
    scene = _scene_or_404(state)
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
async def view_socket(websocket: WebSocket) -> None:
    """The viser websocket, passed through to the loopback server for authenticated users."""
    state: AppState = websocket.app.state.steelscan
    if state.scene is None:
        await websocket.close(code=1008, reason="the 3D view is switched off")
        return
    if not same_origin(websocket, state.settings.allowed_origins):
        await websocket.close(code=1008, reason="cross-site websocket refused")
        return
    token = websocket.query_params.get("token") or websocket.cookies.get(COOKIE)
    if not await anyio.to_thread.run_sync(_allowed, state, token):
        await websocket.close(code=1008, reason="a valid token is required")
        return
    protocols = [
        p.strip()
        for p in websocket.headers.get("sec-websocket-protocol", "").split(",")
        if p.strip()
    ]
    async with connect(
        f"ws://127.0.0.1:{state.scene.port}/",
        subprotocols=protocols or None,  # type: ignore[arg-type]
        max_size=None,
        compression=None,
    ) as upstream:
        await websocket.accept(subprotocol=upstream.subprotocol)

        async def down() -> None:
            async for message in upstream:
                if isinstance(message, bytes):
                    await websocket.send_bytes(message)
                else:
                    await websocket.send_text(message)

        async def up() -> None:
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    return
                await upstream.send(
                    message["bytes"]
                    if message.get("bytes") is not None
                    else message.get("text", "")
                )

        tasks = [asyncio.create_task(down()), asyncio.create_task(up())]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        except (ConnectionClosed, WebSocketDisconnect):
            pass
        finally:
            for t in tasks:
                t.cancel()
    try:
        await websocket.close()
    except RuntimeError:
        pass


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
    markers = []
    for d in mosaic_rows or rows:
        size = max(d.world_w_m or 0.0, d.world_h_m or 0.0)
        text = (
            f"**Defect {d.number or d.id}** — {d.defect_class}  \nlength {d.length_mm or 0:.1f} mm, max width {d.max_width_mm or 0:.2f} mm  \n"
            f"at x {d.world_x_m + (d.world_w_m or 0) / 2:.3f} m, y {d.world_y_m + (d.world_h_m or 0) / 2:.3f} m ({d.source})"
        )
        markers.append(
            DefectMarker(
                d.id,
                d.number or d.id,
                d.defect_class,
                d.world_x_m + (d.world_w_m or 0) / 2,
                d.world_y_m + (d.world_h_m or 0) / 2,
                size,
                text,
            )
        )
    title = f"{s.structure or 'session'} — {session_id[:8]}" if s is not None else session_id
    state.scene.show_session(session_id, points, trajectory, markers, title)  # type: ignore[union-attr]
    return {
        "session_id": session_id,
        "points": 0 if points is None else len(points),
        "trajectory_poses": 0 if trajectory is None else len(trajectory),
        "defects": len(markers),
        "url": "/viser/",
    }


@router.post("/api/sessions/{session_id}/view3d", dependencies=[Depends(require(Role.operator))])
def show_in_3d(db: SessionDep, state: StateDep, session_id: str) -> dict[str, Any]:
    """Show this session in the 3D view: its map coloured by height, its trajectory and a
    marker per defect placed on the structure (click one to see it). Every user sees the
    same view, so changing it needs the operator role."""
    _scene_or_404(state)
    get_session_or_404(db, session_id)
    return session_scene(db, state, session_id)
