"""The live robots in Foxglove: a real station with its Foxglove server on, a client speaking
Foxglove's WebSocket protocol through ``/foxglove``, and a robot sending what it records."""

from __future__ import annotations

import json
import struct
import time
import uuid
from pathlib import Path
from typing import Any

import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect

from robot_link.protocol import MessageType, decode_message
from server.config import Settings
from server.storage.models import Role
from tests.conftest import LiveServer
from tests.media import depth_png, jpeg
from tests.server.helpers import add_user, login, msg, robot_ws

pytestmark = pytest.mark.one_database

SUBPROTOCOL = "foxglove.websocket.v1"
EXPECTED = {
    "/camera/image": ("protobuf", "foxglove.CompressedImage"),
    "/camera/odometry": ("protobuf", "foxglove.PoseInFrame"),
    "/camera/preview": ("protobuf", "foxglove.CompressedImage"),
    "/tof/points": ("protobuf", "foxglove.PointCloud"),
    "/tof/depth": ("protobuf", "foxglove.CompressedImage"),
    "/tof/calibration": ("protobuf", "foxglove.CameraCalibration"),
    "/tof/odometry": ("protobuf", "foxglove.PoseInFrame"),
    "/tf": ("protobuf", "foxglove.FrameTransform"),
    "/robot/telemetry": ("json", None),
}
CALIBRATION = {"camera": {"T_robot_camera": [0.12, 0.0, 0.0]}}


@pytest.fixture
def settings(tmp_path: Path, database_url: str) -> Settings:
    return Settings(
        data_dir=tmp_path / "data",
        job_workers=1,
        database_url=database_url,
        foxglove_port=0,
        view3d=False,
        live_map=False,
        auto_process=False,
    )


def foxglove_url(server: LiveServer) -> str:
    return server.url.replace("http://", "ws://") + "/foxglove"


def viewer_token(server: LiveServer) -> str:
    add_user(server, "ada", Role.viewer)
    return login(server, "ada")["Authorization"].removeprefix("Bearer ")


def hello(ws: ClientConnection) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """The server's serverInfo and its advertised channels by topic."""
    info = json.loads(ws.recv(timeout=10))
    channels: dict[str, dict[str, Any]] = {}
    while set(channels) < set(EXPECTED):
        advertise = json.loads(ws.recv(timeout=10))
        assert advertise["op"] == "advertise", advertise
        channels.update({c["topic"]: c for c in advertise["channels"]})
    return info, channels


def subscribe(ws: ClientConnection, channels: dict[str, dict[str, Any]], topics: list[str]) -> None:
    """Subscribe to ``topics``; the subscription id of each is its index + 1."""
    subscriptions = [{"id": i + 1, "channelId": channels[t]["id"]} for i, t in enumerate(topics)]
    ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
    time.sleep(0.3)  # the server registers them before the robot sends


def message_data(ws: ClientConnection, count: int) -> dict[int, list[tuple[int, bytes]]]:
    """The next ``count`` message-data frames (opcode 1): (log time, payload) by
    subscription id; JSON status messages in between are skipped."""
    out: dict[int, list[tuple[int, bytes]]] = {}
    seen = 0
    while seen < count:
        frame = ws.recv(timeout=10)
        if isinstance(frame, str):
            continue
        assert frame[0] == 0x01, frame[:1]
        sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
        out.setdefault(sub_id, []).append((log_time, frame[13:]))
        seen += 1
    return out


def test_foxglove_lists_the_export_channels_and_sends_what_the_robot_sends(
    live_server: LiveServer,
) -> None:
    token = viewer_token(live_server)
    sid = uuid.uuid4()
    with connect(f"{foxglove_url(live_server)}?token={token}", subprotocols=[SUBPROTOCOL]) as fg:  # type: ignore[list-item]
        assert fg.subprotocol == SUBPROTOCOL
        info, channels = hello(fg)
        assert info["op"] == "serverInfo" and info["name"] == "steelscan"
        for topic, (encoding, schema_name) in EXPECTED.items():
            assert channels[topic]["encoding"] == encoding, topic
            if schema_name is not None:
                assert channels[topic]["schemaName"] == schema_name
                assert channels[topic]["schemaEncoding"] == "protobuf"
                assert channels[topic]["schema"]  # the FileDescriptorSet, base64
            else:
                assert channels[topic]["schemaEncoding"] == "jsonschema"
        topics = ["/camera/image", "/robot/telemetry", "/tof/points", "/camera/preview"]
        subscribe(fg, channels, topics)
        image = jpeg(64, 48)
        with robot_ws(live_server) as robot:
            start = {"structure": "girder 7", "operator": "t", "calibration": CALIBRATION}
            for seq, (mtype, meta, payload) in enumerate(
                [
                    (MessageType.SESSION_START, start, b""),
                    (MessageType.FRAME, {"width": 64, "height": 48}, image),
                    (MessageType.TELEMETRY, {"pose": {"x": 1.0, "y": 2.0, "yaw": 0.5}}, b""),
                    (
                        MessageType.CLOUD,
                        {
                            "encoding": "png16_depth_mm",
                            "width": 8,
                            "height": 6,
                            **{"fx": 5.0, "fy": 5.0, "cx": 4.0, "cy": 3.0},
                        },
                        depth_png(8, 6),
                    ),
                ],
                start=1,
            ):
                robot.send(msg(sid, seq, mtype, meta, payload))
                assert decode_message(robot.recv(timeout=10)).meta["status"] == "stored"
            robot.send(msg(sid, 99, MessageType.VIDEO, {"width": 64, "height": 48}, image))
            got = message_data(fg, 4)
    ((t_frame, frame),) = got[1]
    received = CompressedImage.FromString(frame)
    assert received.data == image and received.format == "jpeg"
    assert received.timestamp.ToNanoseconds() == t_frame
    ((_, telemetry),) = got[2]
    assert json.loads(telemetry)["pose"] == {"x": 1.0, "y": 2.0, "yaw": 0.5}
    ((_, cloud),) = got[3]
    points = PointCloud.FromString(cloud)
    assert points.frame_id == "tof" and len(points.data) == 8 * 6 * 12
    ((_, preview),) = got[4]
    assert CompressedImage.FromString(preview).data == image


def test_a_client_subscribing_to_tf_gets_the_sensor_mounts(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with robot_ws(live_server) as robot:
        start = {"structure": "girder 7", "calibration": CALIBRATION}
        robot.send(msg(sid, 1, MessageType.SESSION_START, start))
        decode_message(robot.recv(timeout=10))
        with connect(foxglove_url(live_server), subprotocols=["foxglove.sdk.v1"]) as fg:  # type: ignore[list-item]
            _, channels = hello(fg)
            subscribe(fg, channels, ["/tf"])
            ((_, mount),) = message_data(fg, 1)[1]
    tf = FrameTransform.FromString(mount)
    assert (tf.parent_frame_id, tf.child_frame_id) == ("base_link", "camera")
    assert tf.translation.x == pytest.approx(0.12)


def test_foxglove_needs_a_valid_token_once_accounts_exist(live_server: LiveServer) -> None:
    token = viewer_token(live_server)
    url = foxglove_url(live_server)
    for refused in (url, f"{url}?token=not-a-token"):
        with pytest.raises(InvalidStatus) as caught:
            connect(refused, subprotocols=[SUBPROTOCOL])  # type: ignore[list-item]
        assert caught.value.response.status_code == 403
    with pytest.raises(InvalidStatus):  # a valid token, but not Foxglove's protocol
        connect(f"{url}?token={token}")
    headers = {"Authorization": f"Bearer {token}"}
    with connect(url, subprotocols=[SUBPROTOCOL], additional_headers=headers) as fg:  # type: ignore[list-item]
        assert json.loads(fg.recv(timeout=10))["op"] == "serverInfo"


def test_foxglove_is_off_by_default_and_on_the_loopback_when_on(live_server: LiveServer) -> None:
    assert Settings.model_fields["foxglove_port"].default is None
    assert Settings.model_fields["foxglove_host"].default == "127.0.0.1"
    assert live_server.app.state.steelscan.foxglove.url.startswith("ws://127.0.0.1:")
