"""Websockets: ``/ws/robot`` for robots (ingest + commands), ``/ws/live`` for browsers."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import struct
import time
import uuid
from typing import Any

import anyio
from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from sqlalchemy.exc import SQLAlchemyError

from robot_link.protocol import (
    HEADER,
    STOP_COMMANDS,
    Message,
    MessageType,
    ProtocolError,
    decode_message,
    encode_message,
)
from server.accounts import accounts_exist, has_role, user_for_token
from server.deps import same_origin
from server.errors import IngestError
from server.models import Role, User
from server.robots import authenticate_robot

log = logging.getLogger(__name__)
router = APIRouter()
IN_FLIGHT = 64


def _bearer(websocket: WebSocket) -> str | None:
    auth = websocket.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return websocket.query_params.get("token")


def _seq_of(data: bytes) -> int:
    """Best-effort seq of an unreadable message, so the robot can drop it; 0 if unknown."""
    try:
        return int(HEADER.unpack_from(data)[5])
    except struct.error:
        return 0


class TokenBucket:
    """At most ``rate`` events a second on average, ``burst`` at once."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate, self.burst = rate, burst
        self.tokens = burst
        self.t = time.monotonic()

    def take(self) -> bool:
        """Spend a token if there is one."""
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.t) * self.rate)
        self.t = now
        if self.tokens < 1:
            return False
        self.tokens -= 1
        return True


class RobotConnection:
    """One robot's websocket: decodes, stores, acknowledges, relays, forwards commands."""

    def __init__(self, websocket: WebSocket, robot_id: int, robot_name: str) -> None:
        self.ws = websocket
        self.robot_id = robot_id
        self.robot_name = robot_name
        self.state = websocket.app.state.steelscan
        self.send_lock = asyncio.Lock()
        self.session_ids: set[str] = set()
        settings = self.state.settings
        self.bucket = TokenBucket(settings.robot_messages_per_s, settings.robot_message_burst)

    async def send(self, message: Message) -> None:
        """Send one protocol message to the robot."""
        data = encode_message(message)
        async with self.send_lock:
            await self.ws.send_bytes(data)

    async def send_error(self, sid: uuid.UUID, seq: int, error: str, *, retry: bool = False) -> None:
        """Tell the robot a message was rejected (``retry``: for now only)."""
        await self.send(Message(MessageType.ERROR, sid, seq, time.time(), {"error": error[:500], "retry": retry}))

    def command_sender(self, sid: uuid.UUID):  # type: ignore[no-untyped-def]
        """A coroutine function the hub calls to forward an operator's command."""
        hub = self.state.hub

        async def send_command(cmd: str, args: dict[str, Any]) -> int:
            seq = hub.next_command_seq(str(sid))
            await self.send(Message(MessageType.COMMAND, sid, seq, time.time(), {"cmd": cmd, "args": args}))
            return seq

        return send_command

    async def run(self) -> None:
        """Serve the robot until it disconnects."""
        senders: dict[str, Any] = {}
        in_flight: set[asyncio.Task[None]] = set()
        room = asyncio.Semaphore(IN_FLIGHT)  # messages of this robot being stored at once
        try:
            while True:
                event = await self.ws.receive()
                if event["type"] == "websocket.disconnect":
                    break
                data = event.get("bytes")
                if data is None:
                    await self.send_error(uuid.UUID(int=0), 0, "text messages are not part of the protocol; send binary")
                    continue
                await room.acquire()
                # handled concurrently (stored by the group-commit writer in arrival order),
                # so the next message is read while this one is being stored
                task = asyncio.create_task(self.handle(data, senders))
                in_flight.add(task)
                task.add_done_callback(lambda t: (in_flight.discard(t), room.release()))
        except WebSocketDisconnect:
            pass
        finally:
            if in_flight:
                await asyncio.gather(*in_flight, return_exceptions=True)
            for sid, sender in senders.items():
                self.state.hub.detach_robot(sid, sender)

    async def handle(self, data: bytes, senders: dict[str, Any]) -> None:
        """Decode, store, acknowledge and relay one message."""
        try:
            message = decode_message(data, max_bytes=self.state.settings.max_message_bytes)
        except ProtocolError as exc:
            await self.send_error(uuid.UUID(int=0), _seq_of(data), f"malformed message: {exc}")
            return
        if message.type in (MessageType.ACK, MessageType.ERROR, MessageType.COMMAND):
            await self.send_error(message.session_id, message.seq, f"{message.type.name} is not sent by robots")
            return
        if message.type is MessageType.VIDEO:  # live preview: relayed, never stored or acknowledged
            if self.bucket.take():
                self.state.hub.publish_frame({"session_id": str(message.session_id), "seq": message.seq, "t": message.timestamp,
                                              "video": True}, message.payload)
            return
        if message.type is MessageType.COMMAND_ACK:
            self.state.hub.publish_json({"type": "command_ack", "session_id": str(message.session_id), "seq": message.seq, **message.meta})
            return
        if not self.bucket.take():
            await self.send_error(message.session_id, message.seq, "rate limit: too many messages, send it again shortly", retry=True)
            return
        try:
            result = await self.state.writer.store(message, self.robot_id)
        except IngestError as exc:
            await self.send_error(message.session_id, message.seq, str(exc), retry=exc.retry)
            return
        except (OSError, SQLAlchemyError) as exc:
            log.exception("ingest: could not store seq %d", message.seq)
            await self.send_error(message.session_id, message.seq, f"ground station could not store it: {type(exc).__name__}")
            return
        await self.send(Message(MessageType.ACK, message.session_id, message.seq, time.time(), {"status": result.status, "of": message.type.name}))
        sid = str(message.session_id)
        if sid not in senders:
            senders[sid] = self.command_sender(message.session_id)
            self.state.hub.attach_robot(sid, senders[sid])
        self.relay(message)
        live_map = self.state.live_map
        if live_map is not None and message.type is MessageType.CLOUD and result.status == "stored":
            live_map.offer(sid, message.payload, message.meta)
        if result.session_ended and self.state.settings.auto_process:
            await anyio.to_thread.run_sync(self.state.jobs.enqueue_pipeline, sid)

    def relay(self, message: Message) -> None:
        """Show the message to watching browsers."""
        hub = self.state.hub
        sid = str(message.session_id)
        pose = message.meta.get("pose")
        if self.state.scene is not None and isinstance(pose, dict) and message.type in (MessageType.FRAME, MessageType.TELEMETRY):
            self.state.scene.show_pose(sid, float(pose["x"]), float(pose["y"]), float(pose["yaw"]))
        if message.type is MessageType.FRAME:
            hub.publish_frame({"session_id": sid, "seq": message.seq, "t": message.timestamp, "pose": message.meta.get("pose")}, message.payload)
        elif message.type is MessageType.TELEMETRY:
            hub.publish_json({"type": "telemetry", "session_id": sid, "data": {**message.meta, "t": message.timestamp}})
        elif message.type in (MessageType.SESSION_START, MessageType.SESSION_END):
            hub.publish_json({"type": "session", "session_id": sid, "event": message.type.name.lower(), "robot": self.robot_name})


@router.websocket("/ws/robot")
async def robot_socket(websocket: WebSocket) -> None:
    """Robot link: binary protocol messages in, ACK/ERROR/COMMAND out (see PROTOCOL.md)."""
    state = websocket.app.state.steelscan
    robot = await anyio.to_thread.run_sync(authenticate_robot, state.factory, _bearer(websocket))
    if robot is None:
        await websocket.close(code=1008, reason="invalid robot token")
        return
    await websocket.accept()
    await RobotConnection(websocket, robot.id, robot.name).run()


@router.websocket("/ws/live")
async def live_socket(websocket: WebSocket) -> None:
    """Browser link: live frames (binary) and events (JSON) out, operator commands in.

    Once accounts exist it needs ``?token=`` (a bearer token); viewers watch, operators command.
    """
    state = websocket.app.state.steelscan
    hub = state.hub
    if not same_origin(websocket, state.settings.allowed_origins):
        await websocket.close(code=1008, reason="cross-site websocket refused: open the dashboard from the station itself")
        return
    user = await anyio.to_thread.run_sync(_browser_user, state.factory, websocket.query_params.get("token"))
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
            size = len(text.encode())
            if size > settings.max_browser_message_bytes:
                await _reply(websocket, ok=False, error=f"a message of {size} bytes is refused: at most {settings.max_browser_message_bytes}")
                continue
            if not bucket.take() and not _is_stop(text):  # stopping the robot is never rate-limited
                await _reply(websocket, ok=False, error=f"too many messages: at most {settings.browser_messages_per_s:g} a second "
                                                        "(stop and e-stop always pass)")
                continue
            if not has_role(user, Role.operator):
                await websocket.send_text(json.dumps({"type": "command_result", "ok": False, "error": f"commands need the operator role; you are {user.role.value}"}))
                continue
            await _handle_browser_message(websocket, hub, watcher, user, text)
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        pump_task.cancel()
        for sid in hub.unwatch(watcher):  # the driver's page went away: stop its robot now
            with contextlib.suppress(KeyError, ProtocolError, RuntimeError, OSError):
                await hub.command(sid, "stop", {"reason": "operator disconnected"})


def _browser_user(factory: Any, token: str | None) -> User | None:
    """The watching user; an anonymous admin while no account exists."""
    with factory() as db:
        if not accounts_exist(db):
            return User(id=0, name="anonymous", password_hash="", role=Role.admin)
        return user_for_token(db, token)


def _is_stop(text: str) -> bool:
    """Whether a browser message is a stop or e-stop command."""
    try:
        request = json.loads(text)
    except json.JSONDecodeError:
        return False
    return isinstance(request, dict) and request.get("cmd") in STOP_COMMANDS


async def _reply(websocket: WebSocket, **fields: Any) -> None:
    await websocket.send_text(json.dumps({"type": "command_result", **fields}))


async def _handle_browser_message(websocket: WebSocket, hub: Any, watcher: Any, user: User, text: str) -> None:
    """One operator message: ``{"type": "control", "session_id", "action": "take"|"release",
    "force"}`` or a command ``{"session_id", "cmd", "args"}``. Anyone with the operator role
    may stop or e-stop; other commands come only from the one browser that drives the robot
    (the first to command a free robot takes it)."""
    try:
        request = json.loads(text)
        if not isinstance(request, dict):
            raise TypeError("a message must be a JSON object")
        sid = str(request["session_id"])
        if request.get("type") == "control":
            action = request.get("action")
            if action not in ("take", "release"):
                raise ValueError("action must be take or release")
        else:
            cmd = str(request["cmd"])
            args = request.get("args") or {}
            if not isinstance(args, dict):
                raise TypeError("args must be an object")
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        await _reply(websocket, ok=False, error=f"bad command: {exc}")
        return
    if request.get("type") == "control":
        if action == "release":
            hub.release_control(sid, watcher)
            await _reply(websocket, ok=True, cmd="release")
            return
        refused = hub.take_control(sid, watcher, force=bool(request.get("force")) and has_role(user, Role.admin))
        await _reply(websocket, ok=not refused, cmd="take", error=refused or None)
        return
    if sid not in hub.robots:
        await _reply(websocket, ok=False, cmd=cmd, error="no robot is connected for that session")
        return
    if cmd not in STOP_COMMANDS:
        refused = hub.take_control(sid, watcher) if hub.controller(sid) in (None, watcher) else \
            f"the robot is driven by {hub.controller(sid).user or 'another operator'}; you can watch, stop or e-stop it"
        if refused:
            await _reply(websocket, ok=False, cmd=cmd, error=refused)
            return
    try:
        seq = await hub.command(sid, cmd, args)
    except KeyError:
        await _reply(websocket, ok=False, cmd=cmd, error="no robot is connected for that session")
    except ProtocolError as exc:
        await _reply(websocket, ok=False, cmd=cmd, error=str(exc))
    else:
        if cmd != "drive":  # drive repeats 20 times a second: its result would only be noise
            await _reply(websocket, ok=True, cmd=cmd, seq=seq)
