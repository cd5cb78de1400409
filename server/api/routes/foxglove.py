"""``/foxglove``: the live robots in Foxglove, through the station. The Foxglove server
(:mod:`server.live.foxglove`) listens on the loopback only; this websocket lets in a
client with a valid bearer token (any role: the stream is read-only) and passes its
connection through, on the station's own port and TLS.

The token comes as ``?token=`` (what the Foxglove app can send: its connection is a URL)
or an ``Authorization: Bearer`` header. Foxglove's protocol is spoken under two names,
``foxglove.sdk.v1`` and, by older apps, ``foxglove.websocket.v1``: either is accepted.
"""

from __future__ import annotations

import anyio
from fastapi import APIRouter, WebSocket
from websockets.asyncio.client import connect
from websockets.typing import Subprotocol

from server.api.accounts import accounts_exist, user_for_token
from server.api.wsproxy import offered_subprotocols, pass_through
from server.live.foxglove import SUBPROTOCOLS
from server.state import AppState

router = APIRouter(tags=["foxglove"])


def _token(websocket: WebSocket) -> str | None:
    scheme, _, credentials = websocket.headers.get("authorization", "").partition(" ")
    if scheme.lower() == "bearer" and credentials.strip():
        return credentials.strip()
    return websocket.query_params.get("token")


def _allowed(state: AppState, token: str | None) -> bool:
    with state.factory() as db:
        return not accounts_exist(db) or user_for_token(db, token) is not None


@router.websocket("/foxglove")
async def foxglove_socket(websocket: WebSocket) -> None:
    """A Foxglove client's websocket, passed through to the live Foxglove server."""
    state: AppState = websocket.app.state.steelscan
    relay = state.foxglove
    if relay is None:
        await websocket.close(
            code=1008, reason="Foxglove is switched off (STEELSCAN_FOXGLOVE_PORT)"
        )
        return
    spoken = [p for p in offered_subprotocols(websocket) if p in SUBPROTOCOLS]
    if not spoken:
        await websocket.close(code=1002, reason=f"speak one of {', '.join(SUBPROTOCOLS)}")
        return
    if not await anyio.to_thread.run_sync(_allowed, state, _token(websocket)):
        await websocket.close(code=1008, reason="a valid token is required: /foxglove?token=...")
        return
    async with connect(
        relay.url,
        subprotocols=[Subprotocol(p) for p in SUBPROTOCOLS],
        max_size=None,
        compression=None,
    ) as upstream:
        await websocket.accept(subprotocol=spoken[0])
        await pass_through(websocket, upstream)
