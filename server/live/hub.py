"""Live relay: robots' frames and telemetry out to watching browsers, commands back in."""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from server.live.coverage_state import LiveCoverage
from server.live.events import (
    Control,
    Event,
    FrameDefects,
    FrameHeader,
    Hello,
    Robot,
    Session,
    Telemetry,
)

SendCommand = Callable[[str, dict[str, Any]], Awaitable[int]]


@dataclass(eq=False)
class Watcher:
    """One browser connection: a bounded queue that drops the oldest item when full."""

    queue: asyncio.Queue[bytes | str] = field(default_factory=lambda: asyncio.Queue(maxsize=8))
    dropped: int = 0
    id: int = 0
    user: str = ""

    def offer(self, item: bytes | str) -> None:
        """Queue an item without ever blocking the robot's ingest."""
        while True:
            try:
                self.queue.put_nowait(item)
                return
            except asyncio.QueueFull:
                self.queue.get_nowait()
                self.dropped += 1


class LiveHub:
    """Knows which robots are connected and which browsers watch; lives in app.state."""

    def __init__(self, queue_size: int = 8) -> None:
        self.queue_size = queue_size
        self.watchers: set[Watcher] = set()
        self.robots: dict[str, SendCommand] = {}  # session id -> command sender
        self.names: dict[str, str] = {}  # session id -> the robot's registered name
        self.drivers: dict[str, list[str]] = {}  # session id -> users who drove its robot
        self.latest: dict[str, dict[str, Any]] = {}  # session id -> last telemetry
        self.coverage = LiveCoverage()  # each live session's trajectory and defects seen
        self.controllers: dict[
            str, Watcher
        ] = {}  # session id -> the one browser that drives its robot
        self._command_seq: dict[str, int] = {}
        self._watcher_ids = itertools.count(1)

    def next_command_seq(self, session_id: str) -> int:
        """Increasing command seq, clock-based so a restarted station never reuses one."""
        seq = max(self._command_seq.get(session_id, 0) + 1, time.time_ns() // 1_000_000)
        self._command_seq[session_id] = seq
        return seq

    def watch(self, user: str = "") -> Watcher:
        """Register a browser; it gets its id, then what is live now: the robots, their
        latest telemetry, who drives them and each live session's coverage map so far (its
        queue holds all of that on top of its usual size)."""
        watcher_id = next(self._watcher_ids)
        greeting: list[Event] = [Hello(watcher_id=watcher_id)]
        greeting += [self._robot_event(sid, connected=True) for sid in self.robots]
        greeting += [Telemetry(session_id=sid, data=t) for sid, t in self.latest.items()]
        greeting += [self._control_event(sid) for sid in self.controllers]
        greeting += self.coverage.events()
        watcher = Watcher(
            queue=asyncio.Queue(maxsize=self.queue_size + len(greeting)), id=watcher_id, user=user
        )
        self.watchers.add(watcher)
        for event in greeting:
            watcher.offer(event.text())
        return watcher

    def unwatch(self, watcher: Watcher) -> list[str]:
        """Forget a browser; the sessions whose robot it was driving (now released)."""
        self.watchers.discard(watcher)
        released = [sid for sid, w in self.controllers.items() if w is watcher]
        for sid in released:
            self.release_control(sid, watcher)
        return released

    def _robot_event(self, session_id: str, *, connected: bool) -> Robot:
        return Robot(
            session_id=session_id, connected=connected, robot=self.names.get(session_id, "")
        )

    def _control_event(self, session_id: str) -> Control:
        w = self.controllers.get(session_id)
        return Control(
            session_id=session_id, holder=w.user if w else None, holder_id=w.id if w else None
        )

    def take_control(self, session_id: str, watcher: Watcher, *, force: bool = False) -> str:
        """Make ``watcher`` the one that drives the robot of a session; '' on success, else
        who holds it. ``force`` (admins) takes it over."""
        holder = self.controllers.get(session_id)
        if holder is not None and holder is not watcher and not force:
            return f"the robot is driven by {holder.user or 'another operator'}"
        self.controllers[session_id] = watcher
        if holder is not watcher:
            self.publish(self._control_event(session_id))
        return ""

    def release_control(self, session_id: str, watcher: Watcher) -> None:
        """Give up driving a robot (only its holder can)."""
        if self.controllers.get(session_id) is watcher:
            del self.controllers[session_id]
            self.publish(self._control_event(session_id))

    def controller(self, session_id: str) -> Watcher | None:
        """The browser that drives the robot of a session, if any."""
        return self.controllers.get(session_id)

    def publish(self, event: Event) -> None:
        """Send an event to every browser (the last telemetry of a live session, its
        trajectory and the defects seen in its frames are kept for browsers that open later;
        an ended session's are dropped)."""
        if isinstance(event, Telemetry):
            self.latest[event.session_id] = event.data
            if isinstance(event.data.get("pose"), dict):
                self.coverage.add_pose(event.session_id, event.data["pose"])
        elif isinstance(event, FrameDefects):
            self.coverage.add_found(event.session_id, event.seq, event.defects)
        elif isinstance(event, Session) and event.event == "session_end":
            self.latest.pop(event.session_id, None)
            self.coverage.forget(event.session_id)
        text = event.text()
        for watcher in list(self.watchers):
            watcher.offer(text)

    def publish_frame(self, header: FrameHeader, jpeg: bytes) -> None:
        """Send a camera frame to every browser."""
        if not self.watchers:
            return
        data = header.pack(jpeg)
        for watcher in list(self.watchers):
            watcher.offer(data)

    def attach_robot(self, session_id: str, sender: SendCommand, name: str = "") -> None:
        """A robot (registered as ``name``) streaming this session can now take commands."""
        self.robots[session_id] = sender
        self.names[session_id] = name
        self.publish(self._robot_event(session_id, connected=True))

    def detach_robot(self, session_id: str, sender: SendCommand) -> None:
        """The robot of this session went away."""
        if self.robots.get(session_id) is sender:
            del self.robots[session_id]
            self.publish(self._robot_event(session_id, connected=False))
            self.names.pop(session_id, None)
            self.latest.pop(session_id, None)

    async def command(self, session_id: str, cmd: str, args: dict[str, Any]) -> int:
        """Forward an operator's command; returns its seq. Raises KeyError if no robot."""
        sender = self.robots[session_id]
        return await sender(cmd, args)
