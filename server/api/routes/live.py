"""The browser's websocket, ``/ws/live``: live frames and events out, operator commands in."""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any

import anyio
from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from robot_link.protocol import STOP_COMMANDS, ProtocolError
from server.api.accounts import accounts_exist, has_role, user_for_token
from server.api.deps import same_origin
from server.limits import TokenBucket
from server.live.events import CommandResult
from server.live.messages import BadBrowserMessage, ControlMessage, is_stop, parse_browser_message
from server.storage.models import InspectionSession, Role, User

router = APIRouter()


@router.websocket("/ws/live")
async def live_socket(websocket: WebSocket) -> None:
    """Browser link: live frames (binary) and events (JSON) out, operator commands in.

    Once accounts exist it needs ``?token=`` (a bearer token); viewers watch, operators command.
    """
    state = websocket.app.state.steelscan
    hub = state.hub
    if not same_origin(websocket, state.settings.allowed_origins):
        await websocket.close(
            code=1008,
            reason="cross-site websocket refused: open the dashboard from the station itself",
        )
        return
    user = await anyio.to_thread.run_sync(
        _browser_user, state.factory, websocket.query_params.get("token")
    )
    if user is None:
        await websocket.close(code=1008, reason="a valid token is required")
        return
    await websocket.accept()
    watcher = hub.watch(user.name)

    async def pump() -> None:
        while True:
            item = await watcher.queue.get()
            if isinstance(item, bytes):
                await websocket.send_bytes(item)
            else:
                await websocket.send_text(item)

    pump_task = asyncio.create_task(pump())
    settings = state.settings
    bucket = TokenBucket(settings.browser_messages_per_s, settings.browser_message_burst)
    try:
        while True:
            text = await websocket.receive_text()
            refused = _refusal(text, user, bucket, settings)
            if refused:
                await _reply(websocket, ok=False, error=refused)
                continue
            await _handle_browser_message(websocket, hub, watcher, user, text)
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        pump_task.cancel()
        for sid in hub.unwatch(watcher):  # the driver's page went away: stop its robot now
            with contextlib.suppress(KeyError, ProtocolError, RuntimeError, OSError):
                await hub.command(sid, "stop", {"reason": "operator disconnected"})


def _refusal(text: str, user: User, bucket: TokenBucket, settings: Any) -> str:
    """Why a browser's message is refused before it is read ('' when it is not): too
    large, over the browser's rate (stopping the robot never is), or from a viewer."""
    size = len(text.encode())
    if size > settings.max_browser_message_bytes:
        return f"a message of {size} bytes is refused: at most {settings.max_browser_message_bytes}"
    if not bucket.take() and not is_stop(text):
        return (
            f"too many messages: at most {settings.browser_messages_per_s:g} a second "
            "(stop and e-stop always pass)"
        )
    if not has_role(user, Role.operator):
        return f"commands need the operator role; you are {user.role.value}"
    return ""


def _browser_user(factory: Any, token: str | None) -> User | None:
    """The watching user; an anonymous admin while no account exists."""
    with factory() as db:
        if not accounts_exist(db):
            return User(id=0, name="anonymous", password_hash="", role=Role.admin)
        return user_for_token(db, token)


async def _note_operator(websocket: WebSocket, session_id: str, name: str) -> None:
    """Record a user who drove the robot as the session's operator (the first one replaces
    what the robot announced; later ones are added)."""
    state = websocket.app.state.steelscan
    drivers = state.hub.drivers.setdefault(session_id, [])
    if name in drivers:
        return
    drivers.append(name)
    await anyio.to_thread.run_sync(_set_operator, state.factory, session_id, ", ".join(drivers))


def _set_operator(factory: Any, session_id: str, operator: str) -> None:
    with factory() as db:
        s = db.get(InspectionSession, session_id)
        if s is not None:
            s.operator = operator[:200]
            db.commit()


async def _reply(websocket: WebSocket, **fields: Any) -> None:
    await websocket.send_text(CommandResult(**fields).text())


async def _handle_browser_message(
    websocket: WebSocket, hub: Any, watcher: Any, user: User, text: str
) -> None:
    """One operator message (:mod:`server.live.messages`). Anyone with the operator role may
    stop or e-stop; other commands come only from the one browser that drives the robot
    (the first to command a free robot takes it)."""
    try:
        request = parse_browser_message(text)
    except BadBrowserMessage as exc:
        await _reply(websocket, ok=False, error=f"bad command: {exc}")
        return
    sid = request.session_id
    if isinstance(request, ControlMessage):
        if request.action == "release":
            hub.release_control(sid, watcher)
            await _reply(websocket, ok=True, cmd="release")
            return
        was = hub.controller(sid)
        refused = hub.take_control(sid, watcher, force=request.force and has_role(user, Role.admin))
        if not refused and was is not watcher:
            await _note_operator(websocket, sid, user.name)
        await _reply(websocket, ok=not refused, cmd="take", error=refused or None)
        return
    cmd, args = request.cmd, request.args
    if sid not in hub.robots:
        await _reply(websocket, ok=False, cmd=cmd, error="no robot is connected for that session")
        return
    if cmd not in STOP_COMMANDS:
        was = hub.controller(sid)
        refused = (
            hub.take_control(sid, watcher)
            if was in (None, watcher)
            else f"the robot is driven by {was.user or 'another operator'}; you can watch, stop or e-stop it"
        )
        if refused:
            await _reply(websocket, ok=False, cmd=cmd, error=refused)
            return
        if was is None:
            await _note_operator(websocket, sid, user.name)
    try:
        seq = await hub.command(sid, cmd, args)
    except KeyError:
        await _reply(websocket, ok=False, cmd=cmd, error="no robot is connected for that session")
    except ProtocolError as exc:
        await _reply(websocket, ok=False, cmd=cmd, error=str(exc))
    else:
        if cmd != "drive":  # drive repeats 20 times a second: its result would only be noise
            await _reply(websocket, ok=True, cmd=cmd, seq=seq)
