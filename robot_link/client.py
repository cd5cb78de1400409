"""The on-board link client: sends messages to the ground station and resends until acknowledged."""

from __future__ import annotations

import asyncio
import logging
import ssl
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import websockets
from websockets.asyncio.client import ClientConnection, connect

from robot_link.inbound import CommandHandler, Inbound
from robot_link.link_state import LinkError as LinkError
from robot_link.link_state import LinkStats, robot_ws_url, stated_limit
from robot_link.protocol import (
    MAX_MESSAGE_BYTES,
    Message,
    MessageType,
    encode_message,
)
from robot_link.replays import CommandGate
from robot_link.spool import Spool

log = logging.getLogger(__name__)
SEQ_BLOCK = 1024  # sequence numbers reserved on disk at a time by a spooling link


class RobotLink(Inbound):
    """Keeps a websocket to the ground station; every message is kept until acknowledged.

    ``send`` returns once the message is queued (at most ``window`` unacknowledged
    messages at a time); on a dropped connection the client reconnects with exponential
    backoff and resends everything not yet acknowledged, in sequence order.

    With a :class:`~robot_link.spool.Spool` every message is on disk before it is first
    sent and stays there until acknowledged: an outage of any length, or a restart of the
    robot's computer, loses nothing (the spool's byte bound replaces the window, and the
    session resumes with its id and sequence numbers).
    """

    def __init__(
        self,
        server_url: str,
        token: str,
        *,
        session_id: uuid.UUID | None = None,
        window: int = 64,
        on_command: CommandHandler | None = None,
        max_backoff_s: float = 5.0,
        spool: Spool | None = None,
        on_link_change: Callable[[bool], None] | None = None,
        ca_file: str | None = None,
    ) -> None:
        self.url = robot_ws_url(server_url)
        # wss://: the station's certificate checked against the system's CAs, or ``ca_file``
        self._ssl = (
            ssl.create_default_context(cafile=ca_file) if self.url.startswith("wss://") else None
        )
        # called with True on (re)connect, False when the link drops
        self.on_link_change = on_link_change
        self._video_busy = False
        self._video_seq = 0
        self.token = token
        self.session_id = session_id or uuid.uuid4()
        self.window = window
        self.on_command = on_command
        self.max_backoff_s = max_backoff_s
        self.stats = LinkStats()
        self._next_seq = 1
        self._unacked: OrderedDict[int, tuple[bytes, float]] = OrderedDict()
        self._transmitted: set[int] = set()  # seqs that went out at least once
        self._space = asyncio.Condition()
        self._ws: ClientConnection | None = None
        self._connected = asyncio.Event()
        self._closing = False
        self._task: asyncio.Task[None] | None = None
        self._fatal: LinkError | None = None
        self.spool = spool
        self._commands = CommandGate()  # stale commands (replays) refused
        self._reserved = 0
        self._warned_full = False
        self._retry_streak = 0  # "retry later" answers since the last ACK
        # the largest message the station takes: its handshake says (until then, the protocol's)
        self.max_message_bytes = MAX_MESSAGE_BYTES
        if spool is not None:
            resumed = spool.load_session()
            if resumed is not None:
                self.session_id, self._next_seq = resumed
            self._next_seq = max([self._next_seq, *(s + 1 for s in spool.pending())])
            for seq in spool.pending():  # never acknowledged before the restart: resend
                self._unacked[seq] = (b"", time.monotonic())
                self._transmitted.add(seq)
            self.stats.spool_bytes = spool.used_bytes

    async def start(self) -> None:
        """Connect in the background (returns at once; sends wait for the connection)."""
        self._task = asyncio.create_task(self._run(), name="robot-link")

    async def close(self) -> None:
        """Stop the link (unacknowledged messages are dropped unless spooled: call ``flush`` first)."""
        self._closing = True
        if self._ws is not None:
            await self._ws.close()
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):
                pass

    def next_seq(self) -> int:
        """Take the next sequence number of this session."""
        seq = self._next_seq
        self._next_seq += 1
        if self.spool is not None and seq >= self._reserved:
            self._reserved = seq + SEQ_BLOCK
            self.spool.save_session(self.session_id, self._reserved)
        return seq

    async def send(
        self,
        mtype: MessageType,
        meta: dict[str, Any] | None = None,
        payload: bytes = b"",
        *,
        timestamp: float | None = None,
    ) -> int:
        """Queue one message for reliable delivery and return its sequence number
        (``timestamp``: when the data was taken, robot clock; default now)."""
        self._raise_if_failed()
        stamp = time.time() if timestamp is None else timestamp
        message = Message(mtype, self.session_id, self.next_seq(), stamp, meta or {}, payload)
        # over the station's limit (ProtocolError): refused here, never queued
        data = encode_message(message, max_bytes=self.max_message_bytes)
        spool = self.spool
        async with self._space:
            if spool is None:
                await self._space.wait_for(
                    lambda: len(self._unacked) < self.window or self._fatal is not None
                )
            else:
                await self._space.wait_for(
                    lambda: spool.room_for(len(data)) or self._fatal is not None
                )
        self._raise_if_failed()
        self._unacked[message.seq] = (data, time.monotonic())
        if spool is not None:
            await asyncio.to_thread(spool.put, message.seq, data)
            self._note_spool()
            if message.seq in self._unacked:  # from now on the bytes live on disk only
                self._unacked[message.seq] = (b"", self._unacked[message.seq][1])
        if await self._transmit(data):
            self._transmitted.add(message.seq)
        return message.seq

    async def notify(self, mtype: MessageType, meta: dict[str, Any], *, seq: int) -> None:
        """Send a message that needs no acknowledgement (COMMAND_ACK); dropped if offline."""
        data = encode_message(Message(mtype, self.session_id, seq, time.time(), meta))
        await self._transmit(data)

    async def send_video(
        self, meta: dict[str, Any], jpeg: bytes, *, timestamp: float | None = None
    ) -> bool:
        """Send a live preview frame (VIDEO): never spooled or resent; dropped when offline or
        while the previous one is still being written (stale video is worth nothing)."""
        if self._video_busy or self._ws is None or not self._connected.is_set():
            self.stats.video_dropped += 1
            return False
        self._video_busy = True
        try:
            self._video_seq += 1
            stamp = time.time() if timestamp is None else timestamp  # when the image was taken
            return await self._transmit(
                encode_message(
                    Message(MessageType.VIDEO, self.session_id, self._video_seq, stamp, meta, jpeg)
                )
            )
        finally:
            self._video_busy = False

    async def flush(self, timeout_s: float = 60.0) -> None:
        """Wait until every message sent so far is acknowledged."""
        try:
            async with self._space:
                await asyncio.wait_for(
                    self._space.wait_for(lambda: not self._unacked or self._fatal is not None),
                    timeout_s,
                )
        except TimeoutError:
            raise LinkError(
                f"{len(self._unacked)} messages still unacknowledged after {timeout_s:g} s"
                + (" (kept in the spool)" if self.spool is not None else "")
            ) from None
        self._raise_if_failed()

    @property
    def pending(self) -> int:
        """Messages sent but not yet acknowledged."""
        return len(self._unacked)

    def _raise_if_failed(self) -> None:
        if self._fatal is not None:
            raise self._fatal

    async def _transmit(self, data: bytes) -> bool:
        """Send now if connected (and the resend after a reconnect is done, so the order
        holds); False if it waits for the (re)connection, which sends it."""
        ws = self._ws
        if ws is None or not self._connected.is_set():
            return False
        try:
            await ws.send(data)
            self.stats.sent += 1
            return True
        except websockets.ConnectionClosed:
            return False  # the reader notices and reconnects; the message stays queued

    async def _run(self) -> None:
        backoff = 0.1
        while not self._closing:
            try:
                headers = {"Authorization": f"Bearer {self.token}"}
                async with connect(
                    self.url,
                    additional_headers=headers,
                    max_size=2**20,
                    open_timeout=10,
                    ssl=self._ssl,
                    # JPEG and PNG payloads do not deflate: compression only costs CPU
                    compression=None,
                ) as ws:
                    self._ws = ws
                    backoff = 0.1
                    self._learn_limit(ws)
                    await self._resend_all(ws)
                    self._connected.set()
                    self._link_changed(True)
                    await self._read(ws)
            except websockets.InvalidStatus as exc:
                status = exc.response.status_code
                if status in (401, 403):
                    await self._fail(
                        LinkError(f"ground station refused the robot token (HTTP {status})")
                    )
                    return
                log.warning("link: ground station answered HTTP %s; retrying", status)
            except ssl.SSLCertVerificationError as exc:  # no retry can make it trusted
                await self._fail(
                    LinkError(
                        f"the ground station's certificate is not trusted ({exc.verify_message}): "
                        "give its certificate (or its CA's) as the CA file"
                    )
                )
                return
            except (OSError, websockets.WebSocketException, asyncio.TimeoutError) as exc:
                if self._closing:
                    return
                log.info("link: connection lost (%s); reconnecting in %.1f s", exc, backoff)
            finally:
                self._ws = None
                if self._connected.is_set():
                    self._connected.clear()
                    self._link_changed(False)
            if self._closing:
                return
            self.stats.reconnects += 1
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, self.max_backoff_s)

    def _learn_limit(self, ws: ClientConnection) -> None:
        """Take the station's message size limit from its handshake's answer."""
        limit = stated_limit(ws.response.headers if ws.response is not None else {})
        if limit is not None and limit != self.max_message_bytes:
            log.info("link: the ground station takes messages of up to %d bytes", limit)
            self.max_message_bytes = limit

    async def _over_limit(self, seq: int, data: bytes) -> bool:
        """Drop a queued message the station would refuse for its size (its limit came down
        since it was queued): resending it could never succeed."""
        if len(data) <= self.max_message_bytes:
            return False
        self.stats.errors += 1
        log.error(
            "link: seq %d is %d bytes, over the ground station's limit of %d: dropped",
            seq,
            len(data),
            self.max_message_bytes,
        )
        await self._drop(seq)
        return True

    async def _drop(self, seq: int) -> None:
        """Forget an unacknowledged message for good (refused: it will never be stored)."""
        self._unacked.pop(seq, None)
        if self.spool is not None:
            self.spool.remove(seq)
        self._transmitted.discard(seq)
        async with self._space:
            self._space.notify_all()

    def _link_changed(self, up: bool) -> None:
        if self.on_link_change is not None:
            try:
                self.on_link_change(up)
            except Exception:  # the robot's own handler must not break the link
                log.exception("link: on_link_change handler failed")

    async def _fail(self, error: LinkError) -> None:
        self._fatal = error
        async with self._space:
            self._space.notify_all()

    def _note_spool(self) -> None:
        assert self.spool is not None
        self.stats.spool_bytes = self.spool.used_bytes
        if self.spool.near_full and not self._warned_full:
            log.warning(
                "link: spool %.0f %% full (%d unacknowledged messages)",
                100 * self.stats.spool_bytes / self.spool.max_bytes,
                len(self.spool),
            )
        self._warned_full = self.spool.near_full

    async def _resend_all(self, ws: ClientConnection) -> None:
        """Send every unacknowledged message, in order, including those queued meanwhile."""
        done: set[int] = set()
        while True:
            todo = [seq for seq in sorted(self._unacked) if seq not in done]
            if not todo:
                return
            for seq in todo:
                data = await self._bytes_of(seq)
                if data is None or await self._over_limit(seq, data):
                    continue
                await ws.send(data)
                done.add(seq)
                self.stats.sent += 1
                if seq in self._transmitted:
                    self.stats.resent += 1
                self._transmitted.add(seq)

    async def _retry(self, seq: int) -> None:
        """Send one unacknowledged message again (after a retryable ERROR)."""
        data = await self._bytes_of(seq)
        if data is None or await self._over_limit(seq, data):
            return
        if await self._transmit(data):
            self.stats.resent += 1

    async def _bytes_of(self, seq: int) -> bytes | None:
        """An unacknowledged message's bytes, from memory or the spool; None once acknowledged."""
        entry = self._unacked.get(seq)
        if entry is None:
            return None
        if not entry[0] and self.spool is not None:
            return await asyncio.to_thread(self.spool.read, seq)
        return entry[0]
