"""The 3D views: one for the live robots and one per finished session a page opened, each
its own viser server, so a reviewer's map never turns into the live robot's scene (or the
other way round). Session views are kept for the last few sessions opened and closed
beyond that."""

from __future__ import annotations

import threading
from collections import OrderedDict

from server.live.scene3d import Scene3D

MAX_SESSION_VIEWS = 4


class Scenes:
    """The live view and the session views (least recently opened closed first)."""

    def __init__(self, live_port: int = 0, max_sessions: int = MAX_SESSION_VIEWS) -> None:
        self.live = Scene3D(live_port)
        self.max_sessions = max_sessions
        self.sessions: OrderedDict[str, Scene3D] = OrderedDict()
        self._lock = threading.Lock()

    def for_session(self, session_id: str) -> Scene3D:
        """The view of a session, started when first asked for."""
        with self._lock:
            scene = self.sessions.pop(session_id, None) or Scene3D()
            self.sessions[session_id] = scene
            evicted = []
            while len(self.sessions) > self.max_sessions:
                evicted.append(self.sessions.popitem(last=False)[1])
        for old in evicted:
            old.close()
        return scene

    def get(self, key: str) -> Scene3D | None:
        """The view ``key`` names: ``live`` or a session id that has a view."""
        if key == "live":
            return self.live
        with self._lock:
            return self.sessions.get(key)

    def close(self) -> None:
        """Stop every viser server."""
        with self._lock:
            scenes = [self.live, *self.sessions.values()]
            self.sessions.clear()
        for scene in scenes:
            scene.close()
