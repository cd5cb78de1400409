"""Defects found in each camera frame while the robot inspects: every stored frame with a
pose is searched in a worker process (the detector would starve the event loop here) and
its defects, placed on the structure through the frame's pose, go to the browsers as a
``frame_defects`` event within about a second of capture. Nothing is stored: the ``detect``
job searches every frame and the mosaic after the session (and when the worker falls
behind, frames are skipped here, not there)."""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np

from server.live.events import FrameDefects
from server.live.worker import LiveWorker

MAX_PENDING = 2  # frames waiting for the worker; beyond, frames are skipped


def _detect(
    jpeg: bytes, camera_pose: list[float], px_per_m: float, method: str
) -> list[dict[str, Any]]:
    """In the worker: the defects of one frame as world boxes (metres)."""
    import cv2

    from processing.detection import find_defects
    from processing.detection.defects import resolved
    from processing.poses import world_box

    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        return []
    found = find_defects(image, 1000.0 / px_per_m, workers=1, method=method)[2]  # type: ignore[arg-type]
    size = (image.shape[1], image.shape[0])
    return [
        {
            "defect_class": d.defect_class,
            "world_box": list(world_box(d.bbox, np.asarray(camera_pose), px_per_m, size)),
            "length_mm": d.length_mm,
            "confidence": d.confidence,
        }
        for d in found
        if resolved(d)  # as the detect job stores them: no specks
    ]


class LiveDetect:
    """Feeds stored frames to the worker and their defects to the browsers."""

    def __init__(
        self, factory: Any, hub: Any, loop: asyncio.AbstractEventLoop, method: str
    ) -> None:
        self.factory = factory
        self.hub = hub
        self.loop = loop
        self.method = method
        self.worker = LiveWorker("live detection", MAX_PENDING)
        self._cameras: dict[str, tuple[float, list[float]] | None] = {}

    def _camera(self, session_id: str) -> tuple[float, list[float]] | None:
        """px_per_m and T_robot_camera of a session's calibration (looked up once)."""
        if session_id not in self._cameras:
            from server.storage.models import InspectionSession

            with self.factory() as db:
                s = db.get(InspectionSession, session_id)
                cam = (s.calibration or {}).get("camera", {}) if s is not None else {}
            ppm = float(cam.get("px_per_m") or 0)
            self._cameras[session_id] = (
                (ppm, list(cam.get("T_robot_camera", [0.0, 0.0, 0.0]))) if ppm > 0 else None
            )
        return self._cameras[session_id]

    def offer(self, session_id: str, seq: int, jpeg: bytes, meta: dict[str, Any]) -> bool:
        """Queue one stored frame; False when it is skipped (no pose or camera scale, or the
        worker is behind)."""
        from processing.poses import compose_se2

        pose, camera = meta.get("pose"), self._camera(session_id)
        if not isinstance(pose, dict) or camera is None:
            return False
        ppm, T_rc = camera
        robot = np.array([float(pose["x"]), float(pose["y"]), float(pose.get("yaw", 0.0))])
        cam = compose_se2(robot, np.asarray(T_rc, dtype=np.float64)).tolist()

        def publish(defects: list[dict[str, Any]]) -> None:  # in the pool's thread
            event = FrameDefects(session_id=session_id, seq=seq, defects=defects)
            self.loop.call_soon_threadsafe(self.hub.publish, event)

        return self.worker.submit(_detect, jpeg, cam, ppm, self.method, done=publish)

    def close(self) -> None:
        """Stop the worker."""
        self.worker.close()
