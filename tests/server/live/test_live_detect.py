"""Defects of each frame while the robot inspects, on the real server: a frame rendered
over one of the simulator's cracks is searched as it arrives, and the browsers get the
crack placed on the structure, where the simulator painted it."""

from __future__ import annotations

import json
import time
import uuid

import cv2
import numpy as np
import pytest
from websockets.sync.client import connect

from robot_link.protocol import Message, MessageType, encode_message
from robot_link.sim.sensors import DownwardCamera
from robot_link.sim.structure import make_structure
from server.config import Settings
from tests.conftest import LiveServer
from tests.server.helpers import robot_ws


@pytest.fixture
def settings(settings: Settings) -> Settings:
    return settings.model_copy(update={"auto_process": False, "view3d": False, "live_detect": True})


def test_a_crack_in_a_frame_reaches_the_browsers_placed_on_the_structure(
    live_server: LiveServer,
) -> None:
    structure = make_structure(3)
    camera = DownwardCamera()
    crack = max(
        (d for d in structure.defects if d.defect_class == "crack"), key=lambda d: d.length_m
    )
    x, y, w, h = crack.bbox_m
    centre = np.array([x + w / 2, y + h / 2, 0.0])
    image = camera.render(structure, centre, np.random.default_rng(1))
    jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 92])[1].tobytes()
    mount = camera.mount_x_m  # the camera sits behind the robot's centre
    pose = {"x": float(centre[0] - mount), "y": float(centre[1]), "yaw": 0.0}
    calibration = {
        "camera": {
            "width": camera.width,
            "height": camera.height,
            "px_per_m": 1 / camera.m_per_px,
            "T_robot_camera": [mount, 0.0, 0.0],
        }
    }
    sid = uuid.uuid4()
    url = live_server.url.replace("http", "ws") + "/ws/live"
    with connect(url) as browser, robot_ws(live_server) as robot:
        robot.send(
            encode_message(
                Message(
                    MessageType.SESSION_START,
                    sid,
                    1,
                    time.time(),
                    {"structure": "girder", "calibration": calibration},
                )
            )
        )
        robot.recv(timeout=10)
        found = []
        for seq in (2, 3):
            meta = {"width": camera.width, "height": camera.height, "pose": pose}
            sent = time.monotonic()
            robot.send(
                encode_message(Message(MessageType.FRAME, sid, seq, time.time(), meta, jpeg))
            )
            robot.recv(timeout=10)
            deadline = sent + 30
            while time.monotonic() < deadline:
                item = browser.recv(timeout=max(0.1, deadline - time.monotonic()))
                event = json.loads(item) if isinstance(item, str) else {}  # bytes: a camera frame
                if event.get("type") == "frame_defects" and event["seq"] == seq:
                    found.append((time.monotonic() - sent, event["defects"]))
                    break
        assert len(found) == 2, found
        latency, defects = found[1]  # the worker has started and loaded its detector
        assert latency < 5.0
        cracks = [d for d in defects if d["defect_class"] == "crack"]
        assert cracks
        bx, by, bw, bh = max(cracks, key=lambda d: d["world_box"][2] * d["world_box"][3])[
            "world_box"
        ]
        # the box found overlaps the painted crack's box on the structure
        assert bx < x + w and x < bx + bw and by < y + h and y < by + bh
