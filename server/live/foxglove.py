"""The live robots in Foxglove: a Foxglove WebSocket server (``foxglove-sdk``) on the
station's loopback, with the channels and schemas of the MCAP export, fed from every robot
message as it arrives. Clients reach it through the station's authenticated ``/foxglove``
websocket (:mod:`server.api.routes.foxglove`); see ``docs/foxglove.md``.

Every live robot's messages go to the same topics (those of the export, and
``/camera/preview`` for the live preview video), stamped with the robot's clock; a message
is only built when a client subscribes to one of its topics.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence

import foxglove
from foxglove import Channel, Context, Schema, StatusLevel
from foxglove.websocket import ChannelView, Client, ServerListener
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

from robot_link.protocol import Message, MessageType
from server.link.ingest import StoreResult
from server.reports.foxglove_messages import (
    CLOUD_TOPICS,
    TOPICS,
    Record,
    cloud_records,
    compressed_image,
    frame_records,
    mount_records,
    ns,
    pose_of,
    schema_bytes,
    telemetry_records,
)

log = logging.getLogger(__name__)

PREVIEW = "/camera/preview"  # the live preview video (VIDEO messages), never stored
LIVE_TOPICS: dict[str, type | None] = {**TOPICS, PREVIEW: CompressedImage}
BACKLOG = 64  # messages buffered per client; a slow one loses its oldest data messages
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")  # one protocol, two names


def _channel(topic: str, message_class: type | None, context: Context) -> Channel:
    if message_class is None:
        return Channel(topic, schema={"type": "object"}, context=context)
    name = message_class.DESCRIPTOR.full_name  # type: ignore[attr-defined]
    schema = Schema(name=name, encoding="protobuf", data=schema_bytes(message_class))
    return Channel(topic, schema=schema, message_encoding="protobuf", context=context)


class FoxgloveRelay:
    """The Foxglove server and its channels, one per topic of :data:`LIVE_TOPICS`."""

    def __init__(self, host: str, port: int, name: str = "steelscan") -> None:
        self.host = host
        self.context = Context()
        self.channels = {t: _channel(t, cls, self.context) for t, cls in LIVE_TOPICS.items()}
        # each live session's sensor transforms and when they were sent
        self._mounts: dict[str, tuple[list[Record], float]] = {}
        self._lock = threading.Lock()
        self.server = foxglove.start_server(
            name=name,
            host=host,
            port=port,
            context=self.context,
            server_listener=_Listener(self),
            supported_encodings=["json", "protobuf"],
            message_backlog_size=BACKLOG,
        )
        self.port = self.server.port

    @property
    def url(self) -> str:
        """Where the station itself connects to the server (the loopback for a wildcard)."""
        host = "127.0.0.1" if self.host in ("", "0.0.0.0", "::") else self.host
        return f"ws://{host}:{self.port}/" if ":" not in host else f"ws://[{host}]:{self.port}/"

    async def on_stored(self, robot: str, message: Message, result: StoreResult) -> None:
        """Called after each stored message's ACK: a new one (not a resend) is sent to the
        subscribed clients; a fault here is logged and never reaches the robot's link."""
        if result.status != "stored":
            return
        try:
            self.show(robot, message)
        except Exception:
            log.exception(
                "foxglove: %s of session %s not sent", message.type.name, message.session_id
            )

    def show_live(self, message: Message) -> None:
        """A live-only message: a VIDEO preview frame goes to ``/camera/preview``."""
        if message.type is MessageType.VIDEO and self.channels[PREVIEW].has_sinks():
            t = message.timestamp
            self._log([(PREVIEW, compressed_image(message.payload, "camera", "jpeg", t))], t)

    def show(self, robot: str, message: Message) -> None:
        """Send a stored robot message on its topics."""
        sid, t, meta = str(message.session_id), message.timestamp, message.meta
        if message.type is MessageType.FRAME:
            if self._watched(("/camera/image", "/camera/odometry")):
                self._log(frame_records(message.payload, pose_of(meta), t), t)
        elif message.type is MessageType.CLOUD:
            if self._watched(CLOUD_TOPICS):
                records, _ = cloud_records(
                    message.payload,
                    str(meta.get("encoding", "")),
                    int(meta.get("width", 0)),
                    int(meta.get("height", 0)),
                    meta,
                    pose_of(meta),
                    t,
                )
                self._log(records, t)
        elif message.type is MessageType.TELEMETRY:
            if self._watched(("/tf", "/robot/telemetry")):
                self._log(telemetry_records(meta, t), t)
        elif message.type is MessageType.SESSION_START:
            mounts = mount_records(meta.get("calibration") or {}, t)
            with self._lock:
                self._mounts[sid] = mounts, t
            self._log(mounts, t)
            structure = meta.get("structure", "")
            self.server.publish_status(
                f"live: {robot} inspecting {structure} (session {sid[:8]})", StatusLevel.Info, sid
            )
        elif message.type is MessageType.SESSION_END:
            with self._lock:
                self._mounts.pop(sid, None)
            self.server.remove_status([sid])

    def resend_mounts(self) -> None:
        """Send every live session's sensor mounts again (a client has just subscribed to
        ``/tf``: transforms sent once at the session's start would never reach it)."""
        with self._lock:
            sessions = list(self._mounts.values())
        for records, t in sessions:
            self._log(records, t)

    def _watched(self, topics: Sequence[str]) -> bool:
        return any(self.channels[t].has_sinks() for t in topics)

    def _log(self, records: list[Record], t: float) -> None:
        for topic, msg in records:
            channel = self.channels[topic]
            data = msg if isinstance(msg, dict) else msg.SerializeToString()
            channel.log(data, log_time=ns(t))

    def close(self) -> None:
        """Stop the server: its clients are disconnected."""
        self.server.stop()
        for channel in self.channels.values():
            channel.close()


class _Listener(ServerListener):
    """What the server tells of its clients: a subscription to ``/tf`` gets the mounts."""

    def __init__(self, relay: FoxgloveRelay) -> None:
        self.relay = relay

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        """A client subscribed to a channel (in the server's own thread)."""
        if channel.topic == "/tf":
            self.relay.resend_mounts()
