"""What a live session's coverage map has drawn so far that a browser opening during the
session needs too: the robot's trajectory (its telemetry poses) and the defects found in
its frames as they arrived. The station keeps them while the session runs and sends each
new browser a ``coverage_state`` per session; the frames' footprints come from the
station's coverage (``GET /api/sessions/{id}/coverage``), which reads the stored frames."""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

from server.live.events import CoverageState

TRAIL_STEP_M = 0.005  # a new point of the trajectory this far from the last (as drawn)
MAX_TRAIL_POINTS = 20_000  # beyond, every other point is dropped (the first and last kept)
MAX_FOUND = 5_000  # defects seen in frames kept per session (the latest)
MAX_SESSIONS = 16  # sessions kept; the least recently updated is forgotten first


@dataclass
class SessionCoverage:
    """One live session's trajectory (x, y in metres) and defects seen in its frames."""

    trail: list[tuple[float, float]] = field(default_factory=list)
    found: list[dict[str, Any]] = field(default_factory=list)


class LiveCoverage:
    """The coverage state of the live sessions."""

    def __init__(self, max_sessions: int = MAX_SESSIONS) -> None:
        self.max_sessions = max_sessions
        self.sessions: OrderedDict[str, SessionCoverage] = OrderedDict()

    def _session(self, session_id: str) -> SessionCoverage:
        kept = self.sessions.pop(session_id, None) or SessionCoverage()
        self.sessions[session_id] = kept
        while len(self.sessions) > self.max_sessions:
            self.sessions.popitem(last=False)
        return kept

    def add_pose(self, session_id: str, pose: dict[str, Any]) -> None:
        """A telemetry pose: the trajectory grows when the robot moved ``TRAIL_STEP_M``."""
        try:
            x, y = float(pose["x"]), float(pose["y"])
        except (KeyError, TypeError, ValueError):
            return
        if not (math.isfinite(x) and math.isfinite(y)):
            return
        trail = self._session(session_id).trail
        if trail and math.hypot(x - trail[-1][0], y - trail[-1][1]) <= TRAIL_STEP_M:
            return
        trail.append((x, y))
        if len(trail) > MAX_TRAIL_POINTS:
            trail[:] = trail[:-1:2] + trail[-1:]

    def add_found(self, session_id: str, seq: int, defects: list[dict[str, Any]]) -> None:
        """The defects found in one frame (``frame_defects``)."""
        if not defects:
            return
        found = self._session(session_id).found
        found.extend({"seq": seq, **d} for d in defects)
        del found[:-MAX_FOUND]

    def forget(self, session_id: str) -> None:
        """The session ended."""
        self.sessions.pop(session_id, None)

    def events(self) -> list[CoverageState]:
        """What a browser opening now gets: one event per live session kept."""
        return [
            CoverageState(session_id=sid, trail=[list(p) for p in s.trail], found=s.found)
            for sid, s in self.sessions.items()
        ]
