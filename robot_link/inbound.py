"""What the ground station sends a robot's link: acknowledgements (the message is stored,
forget it), errors (send it again later, or drop it for good) and the operator's commands
(admitted once, never replayed)."""

from __future__ import annotations

import asyncio
import logging
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from typing import Any

from websockets.asyncio.client import ClientConnection

from robot_link.link_state import LinkStats
from robot_link.protocol import Message, MessageType, ProtocolError, decode_message
from robot_link.replays import CommandGate
from robot_link.spool import Spool

log = logging.getLogger("robot_link.client")
RETRY_S = 0.2  # wait before sending again a message the station could not store yet (doubled
# with each such answer in a row, up to ``max_backoff_s``)

CommandHandler = Callable[[Message], Awaitable[None] | None]


class Inbound:
    """The link's reading side (a part of :class:`robot_link.client.RobotLink`)."""

    _unacked: OrderedDict[int, tuple[bytes, float]]
    _transmitted: set[int]
    _space: asyncio.Condition
    _retry_streak: int
    _commands: CommandGate
    spool: Spool | None
    stats: LinkStats
    max_backoff_s: float
    on_command: CommandHandler | None

    async def _retry(self, seq: int) -> None:
        raise NotImplementedError

    async def _drop(self, seq: int) -> None:
        raise NotImplementedError

    def _note_spool(self) -> None:
        raise NotImplementedError

    async def notify(self, mtype: MessageType, meta: dict[str, Any], *, seq: int) -> None:
        raise NotImplementedError

    async def _read(self, ws: ClientConnection) -> None:
        async for raw in ws:
            if isinstance(raw, str):
                log.warning("link: ignoring a text message from the ground station")
                continue
            try:
                message = decode_message(raw)
            except ProtocolError as exc:
                log.warning("link: bad message from the ground station: %s", exc)
                continue
            await self._handle(message)

    async def _handle(self, message: Message) -> None:
        if message.type is MessageType.ACK:
            self._retry_streak = 0
            entry = self._unacked.pop(message.seq, None)
            self._transmitted.discard(message.seq)
            if self.spool is not None:
                self.spool.remove(message.seq)
                self._note_spool()
            if entry is not None:
                self.stats.acked += 1
                self.stats.last_ack_latency_s = time.monotonic() - entry[1]
                if message.meta.get("status") == "duplicate":
                    self.stats.duplicates += 1
            async with self._space:
                self._space.notify_all()
        elif (
            message.type is MessageType.ERROR
            and message.meta.get("retry")
            and message.seq in self._unacked
        ):
            self.stats.errors += 1
            delay = min(RETRY_S * 2**self._retry_streak, self.max_backoff_s)
            self._retry_streak = min(self._retry_streak + 1, 16)
            log.info(
                "link: seq %d not stored yet (%s); sending it again in %.1f s",
                message.seq,
                message.meta.get("error"),
                delay,
            )
            asyncio.get_running_loop().call_later(
                delay, lambda seq: asyncio.ensure_future(self._retry(seq)), message.seq
            )
        elif message.type is MessageType.ERROR:
            self.stats.errors += 1
            log.error(
                "link: ground station rejected seq %d: %s", message.seq, message.meta.get("error")
            )
            # A rejected message will never be accepted: drop it so flush() can finish.
            await self._drop(message.seq)
        elif message.type is MessageType.COMMAND and self.on_command is not None:
            if not self._commands.admit(message):  # a replay: refused, never acted on twice
                cmd = str(message.meta.get("cmd"))
                await self.notify(
                    MessageType.COMMAND_ACK, {"cmd": cmd, "accepted": False}, seq=message.seq
                )
                return
            result = self.on_command(message)
            if asyncio.iscoroutine(result):
                await result
