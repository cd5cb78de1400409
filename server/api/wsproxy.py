"""A browser's websocket passed through to a loopback server of the station's own (the 3D
views' viser servers, the live Foxglove server), both ways, until either side goes."""

from __future__ import annotations

import asyncio
import contextlib

from fastapi import WebSocket, WebSocketDisconnect
from starlette.websockets import WebSocketState
from websockets.asyncio.client import ClientConnection
from websockets.exceptions import ConnectionClosed


def offered_subprotocols(websocket: WebSocket) -> list[str]:
    """The subprotocols a client's handshake offers, in its order."""
    header = websocket.headers.get("sec-websocket-protocol", "")
    return [p.strip() for p in header.split(",") if p.strip()]


async def pass_through(websocket: WebSocket, upstream: ClientConnection) -> None:
    """Relay messages between an accepted ``websocket`` and ``upstream`` as they are (text
    as text, binary as binary), then close the client's side if it is still open."""

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
                message["bytes"] if message.get("bytes") is not None else message.get("text", "")
            )

    tasks = [asyncio.create_task(down()), asyncio.create_task(up())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()
        # a side that went away ends its task with an error: expected, not worth a log
        await asyncio.gather(*tasks, return_exceptions=True)
    if websocket.client_state == WebSocketState.CONNECTED:
        with contextlib.suppress(RuntimeError, OSError, WebSocketDisconnect, ConnectionClosed):
            await websocket.close()
