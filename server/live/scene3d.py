"""The 3D view: a viser server showing one session's map, trajectory, live robot pose and
defects on the structure.

viser runs its own HTTP + websocket server in a daemon thread; it is bound to loopback
(it has no authentication) and reached through the ground station's ``/viser/`` proxy,
which checks the user (``server.api.routes.view3d``). The heavy work (ICP) runs in job worker
processes, so this process stays free to serve the view. Positions are sent as float32
(viser's float16 default would round millimetres away). World frame: x along the plate,
y across it, z down into it (so "up" is -z).
"""

from __future__ import annotations

import contextlib
import io
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import viser
from numpy.typing import NDArray

log = logging.getLogger(__name__)

MAX_DISPLAY_POINTS = 300_000
POSE_HZ = 20.0
CLASS_COLOURS = {"crack": (230, 40, 40), "corrosion": (240, 140, 20)}


@dataclass(frozen=True)
class DefectMarker:
    """A defect placed on the structure (metres, world frame)."""

    id: int
    number: int
    defect_class: str
    x: float
    y: float
    size: float
    text: str


def height_colours(points: NDArray[np.floating]) -> NDArray[np.uint8]:
    """RGB colour of each point by its height above the plate (-z), viridis."""
    h = -np.asarray(points, dtype=np.float64)[:, 2]
    lo, hi = np.percentile(h, [2, 98]) if len(h) else (0.0, 1.0)
    level = np.clip((h - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
    bgr = cv2.applyColorMap(level.reshape(-1, 1), cv2.COLORMAP_VIRIDIS).reshape(-1, 3)
    return bgr[:, ::-1].copy()


def display_points(
    points: NDArray[np.floating], limit: int = MAX_DISPLAY_POINTS, seed: int = 0
) -> NDArray[np.float32]:
    """At most ``limit`` points of a map for display (a random subset: even coverage)."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) > limit:
        pts = pts[np.random.default_rng(seed).choice(len(pts), limit, replace=False)]
    return pts


class Scene3D:
    """One viser server; shows one session at a time."""

    def __init__(self, port: int = 0) -> None:
        banner = io.StringIO()
        # viser prints a banner whatever ``verbose`` says; stdout is the CLI's
        with contextlib.redirect_stdout(banner):
            self.server = viser.ViserServer(
                host="127.0.0.1", port=port, label="steelscan 3D", verbose=False
            )
        log.debug("viser: %s", banner.getvalue())
        self.server.scene.set_up_direction("-z")
        self.session_id: str | None = None
        self._lock = threading.Lock()
        self._trail: list[tuple[float, float]] = []
        self._last_pose_t = 0.0
        self.live_map_points = 0  # points of the live map last shown
        self.live_trajectory_poses = 0  # poses of the live map's trajectory last shown
        self._closed = False
        self._info = self.server.gui.add_markdown("Click a defect marker to see it.")
        self.markers: dict[int, DefectMarker] = {}
        self.focused: int | None = None  # the defect the view last flew to
        self.moment: tuple[float, float, float] | None = None  # the robot's pose on view
        self._moment_text: Any = None  # the moment's words, below the defect's
        # called with a defect's id when a browser clicks its marker (the dashboard selects it)
        self.on_select: Callable[[int], None] | None = None
        self._title = self.server.gui.add_markdown("**No session shown yet.**")
        self._live_label = ""  # the live session's robot (its session id without a name)

    @property
    def port(self) -> int:
        """Where the viser server listens (loopback)."""
        return int(self.server.get_port())

    def show_session(
        self,
        session_id: str,
        points: NDArray[np.floating] | None,
        trajectory: NDArray[np.floating] | None,
        defects: Sequence[DefectMarker],
        title: str = "",
    ) -> None:
        """Replace the scene with a session's map, trajectory and defect markers."""
        with self._lock:
            self.session_id = session_id
            self._trail = []
            scene = self.server.scene
            scene.reset()
            self.markers = {}
            self._title.content = f"**{title or session_id}**"
            if points is not None and len(points):
                pts = display_points(points)
                scene.add_point_cloud(
                    "/map", pts, height_colours(pts), point_size=0.006, precision="float32"
                )
                self._frame_view(pts)
            if trajectory is not None and len(trajectory) > 1:
                scene.add_spline_catmull_rom(
                    "/trajectory",
                    np.asarray(trajectory, dtype=np.float32),
                    color=(30, 110, 240),
                    thickness=0.004,
                )
            for d in defects:
                self._add_marker(d)

    def _frame_view(self, pts: NDArray[np.float32]) -> None:
        """Point new browsers' cameras at the map, from above and to the side."""
        lo, hi = np.percentile(pts, [2, 98], axis=0)
        centre = (lo + hi) / 2
        span = float(np.linalg.norm(hi - lo))
        camera = self.server.initial_camera
        camera.look_at = tuple(float(v) for v in centre)
        camera.position = (
            float(centre[0]),
            float(centre[1] - 0.6 * span),
            float(centre[2] - 0.7 * span),
        )
        for client in self.server.get_clients().values():
            client.camera.look_at = camera.look_at
            client.camera.position = camera.position

    def _add_marker(self, d: DefectMarker) -> None:
        """A defect's sphere on the structure and its number just above it. The label is the
        sphere's child in viser's scene tree ("/defects/7/label" under "/defects/7"), so its
        position is relative to the sphere: straight up (-z) from it."""
        radius = float(np.clip(d.size / 2, 0.008, 0.06))
        handle = self.server.scene.add_icosphere(
            f"/defects/{d.id}",
            radius=radius,
            color=CLASS_COLOURS.get(d.defect_class, (200, 200, 200)),
            position=(d.x, d.y, -0.004),
            opacity=0.8,
        )
        self.server.scene.add_label(
            f"/defects/{d.id}/label", f"{d.number}", position=(0.0, 0.0, -radius - 0.01)
        )

        self.markers[d.id] = d

        @handle.on_click
        def _(_: Any) -> None:
            self._info.content = d.text
            if self.on_select is not None:
                self.on_select(d.id)

    def focus(self, defect_id: int) -> bool:
        """Fly every browser's camera to a defect's marker (from above, close enough to see
        its neighbourhood) and show its text; False when the view has no such marker."""
        d = self.markers.get(defect_id)
        if d is None:
            return False
        self.focused = defect_id
        self._info.content = d.text
        span = max(d.size * 6, 0.25)
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.look_at = (d.x, d.y, 0.0)
                client.camera.position = (d.x, d.y - 0.4 * span, -0.9 * span)
        return True

    def _robot(self, name: str, x: float, y: float, yaw: float) -> None:
        """The robot's axes and its downward camera's frustum at a pose (caller holds the
        lock)."""
        q = (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))
        self.server.scene.add_frame(
            name, wxyz=q, position=(x, y, -0.05), axes_length=0.08, axes_radius=0.004
        )
        self.server.scene.add_camera_frustum(
            f"{name}/camera",
            fov=np.radians(60),
            aspect=4 / 3,
            scale=0.06,
            color=(250, 200, 0),
            wxyz=(0.0, 1.0, 0.0, 0.0),
            position=(0.0, 0.0, 0.0),
        )

    def show_moment(self, x: float, y: float, yaw: float, label: str = "") -> None:
        """Place the robot at one moment of the session on view (a reviewer scrubbing its
        timeline): its axes and camera at the pose, ``label`` (the moment) in the panel
        below the selected defect's text.
        The session's map, trajectory and markers stay as they are."""
        with self._lock:
            if self._closed:
                return
            self._robot("/moment", x, y, yaw)
            self.moment = (x, y, yaw)
            if self._moment_text is None:
                self._moment_text = self.server.gui.add_markdown("")
            self._moment_text.content = (
                f"Robot at {label}" if label else "Robot at the moment shown"
            )

    def show_pose(self, session_id: str, x: float, y: float, yaw: float, robot: str = "") -> None:
        """Move the robot marker (and grow its trail) for the session being shown; a new
        live session takes over the view, titled by its ``robot``'s name. At most
        ``POSE_HZ`` updates a second reach the browsers (a robot may report far more
        often)."""
        now = time.monotonic()
        if session_id == self.session_id and now - self._last_pose_t < 1.0 / POSE_HZ:
            return
        self._last_pose_t = now
        with self._lock:
            if session_id != self.session_id:
                self.session_id = session_id
                self._trail = []
                self.live_map_points = 0
                self.live_trajectory_poses = 0
                self.server.scene.reset()
                self._live_label = robot or session_id
                self._title.content = f"**Live: {self._live_label}**"
            self._robot("/robot", x, y, yaw)
            if not self._trail or np.hypot(x - self._trail[-1][0], y - self._trail[-1][1]) > 0.01:
                self._trail.append((x, y))
                if len(self._trail) > 1:
                    pts = np.array([[px, py, -0.002] for px, py in self._trail], dtype=np.float32)
                    self.server.scene.add_line_segments(
                        "/live_trail",
                        np.stack([pts[:-1], pts[1:]], axis=1),
                        colors=(250, 200, 0),
                        thickness=0.004,
                    )

    def show_live_map(
        self,
        session_id: str,
        points: NDArray[np.floating],
        clouds: int,
        trajectory: NDArray[np.floating] | None = None,
    ) -> None:
        """Show the map growing during a live session (when that session is on view), with
        the ToF's trajectory as the map's pose graph places it (blue; the odometry's trail
        is yellow)."""
        with self._lock:
            if self._closed or session_id != self.session_id or not len(points):
                return
            pts = np.asarray(points, dtype=np.float32)
            self.server.scene.add_point_cloud(
                "/live_map", pts, height_colours(pts), point_size=0.006, precision="float32"
            )
            if trajectory is not None and len(trajectory) > 1:
                path = np.asarray(trajectory, dtype=np.float32)
                self.server.scene.add_line_segments(
                    "/live_trajectory",
                    np.stack([path[:-1], path[1:]], axis=1),
                    colors=(30, 110, 240),
                    thickness=0.004,
                )
                self.live_trajectory_poses = len(path)
            self._title.content = (
                f"**Live: {self._live_label}** — map of {clouds} clouds, {len(pts)} points"
            )
            if not self.live_map_points:
                self._frame_view(pts)
            self.live_map_points = len(pts)

    def clients(self) -> int:
        """Browsers connected to the view."""
        return len(self.server.get_clients())

    def close(self) -> None:
        """Stop the viser server (quietly: it announces that on stdout too)."""
        with self._lock:
            self._closed = True
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()
