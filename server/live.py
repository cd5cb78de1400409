"""Live relay: robots' frames and telemetry out to watching browsers, commands back in."""

from __future__ import annotations

import asyncio
import json
import struct
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

SendCommand = Callable[[str, dict[str, Any]], Awaitable[int]]


@dataclass(eq=False)
class Watcher:
    """One browser connection: a bounded queue that drops the oldest item when full."""

    queue: asyncio.Queue[bytes | str] = field(default_factory=lambda: asyncio.Queue(maxsize=8))
    dropped: int = 0

    def offer(self, item: bytes | str) -> None:
        """Queue an item without ever blocking the robot's ingest."""
        while True:
            try:
                self.queue.put_nowait(item)
                return
            except asyncio.QueueFull:
                self.queue.get_nowait()
                self.dropped += 1


def pack_frame(header: dict[str, Any], jpeg: bytes) -> bytes:
    """Binary message for a browser: u32 header length, JSON header, JPEG bytes."""
    head = json.dumps(header, separators=(",", ":")).encode()
    return struct.pack("<I", len(head)) + head + jpeg


class LiveHub:
    """Knows which robots are connected and which browsers watch; lives in app.state."""

    def __init__(self, queue_size: int = 8) -> None:
        self.queue_size = queue_size
        self.watchers: set[Watcher] = set()
        self.robots: dict[str, SendCommand] = {}  # session id -> command sender
        self.latest: dict[str, dict[str, Any]] = {}  # session id -> last telemetry
        self._command_seq: dict[str, int] = {}

    def next_command_seq(self, session_id: str) -> int:
        """Increasing command seq, clock-based so a restarted station never reuses one."""
        seq = max(self._command_seq.get(session_id, 0) + 1, time.time_ns() // 1_000_000)
        self._command_seq[session_id] = seq
        return seq

    def watch(self) -> Watcher:
        """Register a browser."""
        watcher = Watcher(queue=asyncio.Queue(maxsize=self.queue_size))
        self.watchers.add(watcher)
        for sid, telemetry in self.latest.items():
            watcher.offer(json.dumps({"type": "telemetry", "session_id": sid, "data": telemetry}))
        return watcher

    def unwatch(self, watcher: Watcher) -> None:
        """Forget a browser."""
        self.watchers.discard(watcher)

    def publish_json(self, event: dict[str, Any]) -> None:
        """Send a JSON event to every browser."""
        if event.get("type") == "telemetry":
            self.latest[event["session_id"]] = event["data"]
        text = json.dumps(event, separators=(",", ":"))
        for watcher in list(self.watchers):
            watcher.offer(text)

    def publish_frame(self, header: dict[str, Any], jpeg: bytes) -> None:
        """Send a camera frame to every browser."""
        if not self.watchers:
            return
        data = pack_frame(header, jpeg)
        for watcher in list(self.watchers):
            watcher.offer(data)

    def attach_robot(self, session_id: str, sender: SendCommand) -> None:
        """A robot streaming this session can now take commands."""
        self.robots[session_id] = sender
        self.publish_json({"type": "robot", "session_id": session_id, "connected": True})

    def detach_robot(self, session_id: str, sender: SendCommand) -> None:
        """The robot of this session went away."""
        if self.robots.get(session_id) is sender:
            del self.robots[session_id]
            self.publish_json({"type": "robot", "session_id": session_id, "connected": False})

    async def command(self, session_id: str, cmd: str, args: dict[str, Any]) -> int:
        """Forward an operator's command; returns its seq. Raises KeyError if no robot."""
        sender = self.robots[session_id]
        return await sender(cmd, args)
