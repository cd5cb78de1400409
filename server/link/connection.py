"""A robot's websocket, ``/ws/robot``: decode, store, acknowledge, relay, forward commands."""

from __future__ import annotations

import asyncio
import logging
import struct
import time
import uuid
from typing import Any

import anyio
from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from robot_link.protocol import (
    HEADER,
    MAX_BYTES_HEADER,
    Message,
    MessageType,
    ProtocolError,
    decode_message,
    encode_message,
)
from server.errors import IngestError
from server.limits import TokenBucket
from server.link.ingest import StoreResult
from server.link.robots import authenticate_robot, hash_token
from server.storage.space import is_disk_full

log = logging.getLogger(__name__)
router = APIRouter()
IN_FLIGHT = 64
FULL_LOG_INTERVAL_S = 10.0  # a full disk is logged at most this often (every message hits it)
_full_logged = -float("inf")


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


class RobotConnection:
    """One robot's websocket: decodes, stores, acknowledges, relays, forwards commands."""

    def __init__(
        self, websocket: WebSocket, robot_id: int, robot_name: str, token_digest: str = ""
    ) -> None:
        self.ws = websocket
        self.robot_id = robot_id
        self.robot_name = robot_name
        self.token_digest = token_digest
        self.state = websocket.app.state.steelscan
        self.send_lock = asyncio.Lock()
        self.owned: set[str] = set()  # sessions this robot recorded
        self.refused: dict[str, float] = {}  # sessions it did not: when last looked up
        settings = self.state.settings
        self.bucket = TokenBucket(settings.robot_messages_per_s, settings.robot_message_burst)
        self.cut_off = False

    async def send(self, message: Message) -> None:
        """Send one protocol message to the robot."""
        data = encode_message(message)
        async with self.send_lock:
            await self.ws.send_bytes(data)

    async def send_error(
        self, sid: uuid.UUID, seq: int, error: str, *, retry: bool = False
    ) -> None:
        """Tell the robot a message was rejected (``retry``: for now only)."""
        await self.send(
            Message(
                MessageType.ERROR, sid, seq, time.time(), {"error": error[:500], "retry": retry}
            )
        )

    def command_sender(self, sid: uuid.UUID):  # type: ignore[no-untyped-def]
        """A coroutine function the hub calls to forward an operator's command."""
        hub = self.state.hub

        async def send_command(cmd: str, args: dict[str, Any]) -> int:
            seq = hub.next_command_seq(str(sid))
            await self.send(
                Message(MessageType.COMMAND, sid, seq, time.time(), {"cmd": cmd, "args": args})
            )
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
                    await self.send_error(
                        uuid.UUID(int=0),
                        0,
                        "text messages are not part of the protocol; send binary",
                    )
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
        """One message: admitted, stored, acknowledged, then handed on."""
        within_rate = self.bucket.take()  # every message counts, readable or not
        message = await self.admit(data, within_rate)
        if message is None:
            return
        result = await self.store(message)
        if result is None:
            return
        await self.send(
            Message(
                MessageType.ACK,
                message.session_id,
                message.seq,
                time.time(),
                {"status": result.status, "of": message.type.name},
            )
        )
        sid = str(message.session_id)
        self.owned.add(sid)  # ingest checked the owner
        if sid not in senders:
            senders[sid] = self.command_sender(message.session_id)
            self.state.hub.attach_robot(sid, senders[sid], self.robot_name)
        for subscriber in self.state.on_stored:  # the live views, then the jobs
            await subscriber(self.robot_name, message, result)

    async def admit(self, data: bytes, within_rate: bool) -> Message | None:
        """The decoded message if it is to be stored; None when it was answered here
        (malformed, not a robot's to send, over the rate) or is live only (VIDEO,
        COMMAND_ACK: relayed to the browsers, never stored)."""
        try:
            message = decode_message(data, max_bytes=self.state.settings.max_message_bytes)
        except ProtocolError as exc:
            if not self.state.malformed.malformed(self.robot_id, self.token_digest):  # barred
                if not self.cut_off:
                    self.cut_off = True
                    log.warning("robot %s: too many malformed messages, barred", self.robot_name)
                    await self.ws.close(code=1008, reason="too many malformed messages")
            elif within_rate:
                await self.send_error(uuid.UUID(int=0), _seq_of(data), f"malformed message: {exc}")
            return None
        if message.type in (MessageType.ACK, MessageType.ERROR, MessageType.COMMAND):
            await self.send_error(
                message.session_id, message.seq, f"{message.type.name} is not sent by robots"
            )
            return None
        if message.type in (MessageType.VIDEO, MessageType.COMMAND_ACK):
            # live only, never stored: to the browsers (a live preview over the rate is
            # dropped; another robot's live channel is never relayed)
            owned = await self.owns(str(message.session_id))
            if owned and (within_rate or message.type is MessageType.COMMAND_ACK):
                for show in self.state.on_live:
                    show(message)
            return None
        if not within_rate:
            await self.send_error(
                message.session_id,
                message.seq,
                "rate limit: too many messages, send it again shortly",
                retry=True,
            )
            return None
        return message

    async def store(self, message: Message) -> StoreResult | None:
        """Store the message; None when it was refused, the robot told why and whether to
        send it again."""
        try:
            return await self.state.writer.store(message, self.robot_id)
        except IngestError as exc:
            await self.send_error(message.session_id, message.seq, str(exc), retry=exc.retry)
        except Exception as exc:  # noqa: BLE001  the station's own fault: never "dropped"
            if self.state.ingest.refuses_value(exc):  # the same message fails every time
                error, retry = f"a value cannot be stored: {_first_line(exc)}", False
            elif is_disk_full(exc):
                _log_disk_full(exc)
                error, retry = "ground station storage is full: retry later", True
            else:
                log.exception("ingest: could not store seq %d", message.seq)
                error = f"ground station could not store it ({type(exc).__name__}): retry later"
                retry = True
            await self.send_error(message.session_id, message.seq, error, retry=retry)
        return None

    async def owns(self, sid: str) -> bool:
        """Whether this robot recorded session ``sid`` (looked up at most once a second for
        a session it did not)."""
        if sid in self.owned:
            return True
        if time.monotonic() - self.refused.get(sid, -1.0) < 1.0:
            return False
        robot = await anyio.to_thread.run_sync(self.state.ingest.robot_of, sid)
        if robot == self.robot_id:
            self.owned.add(sid)
            return True
        if sid not in self.refused:
            log.warning(
                "robot %s: live messages for session %s, not its own, dropped", self.robot_name, sid
            )
        self.refused[sid] = time.monotonic()
        return False


def _first_line(exc: BaseException) -> str:
    orig = getattr(exc, "orig", None) or exc
    return (str(orig).splitlines() or [type(orig).__name__])[0][:300]


def _log_disk_full(exc: BaseException) -> None:
    """One warning, without a traceback, per FULL_LOG_INTERVAL_S while the disk is full."""
    global _full_logged
    now = time.monotonic()
    if now - _full_logged >= FULL_LOG_INTERVAL_S:
        _full_logged = now
        log.warning("ingest: the data directory's disk is full (%s); robots asked to retry", exc)


@router.websocket("/ws/robot")
async def robot_socket(websocket: WebSocket) -> None:
    """Robot link: binary protocol messages in, ACK/ERROR/COMMAND out (see docs/protocol.md)."""
    state = websocket.app.state.steelscan
    token = _bearer(websocket)
    digest = hash_token(token or "")
    if state.malformed.token_barred(digest):  # refused before the upgrade and the database
        await websocket.close(code=1008, reason="barred for malformed messages; retry later")
        return
    robot = await anyio.to_thread.run_sync(authenticate_robot, state.factory, token)
    if robot is None:
        await websocket.close(code=1008, reason="invalid robot token")
        return
    if state.malformed.barred_for(robot.id) > 0:  # refused before the upgrade: cheap
        await websocket.close(code=1008, reason="barred for malformed messages; retry later")
        return
    limit = str(state.settings.max_message_bytes).encode()
    await websocket.accept(headers=[(MAX_BYTES_HEADER.lower().encode(), limit)])
    await RobotConnection(websocket, robot.id, robot.name, digest).run()
