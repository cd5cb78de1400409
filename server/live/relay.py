"""What a robot message shows live: a stored one's frame and telemetry to the watching
browsers, the robot's pose in the live 3D view, its cloud and frame to the live map and its
frame to live detection; a live-only one (a preview frame, a command's answer) to the browsers."""

from __future__ import annotations

from robot_link.protocol import Message, MessageType
from server.link.ingest import StoreResult
from server.live.events import CommandAck, FrameHeader, Session, Telemetry
from server.live.hub import LiveHub
from server.live.live_detect import LiveDetect
from server.live.live_map import LiveMap
from server.live.scenes import Scenes


class LiveRelay:
    """Fans a stored message out to the live views that are switched on."""

    def __init__(
        self,
        hub: LiveHub,
        scenes: Scenes | None,
        live_map: LiveMap | None,
        live_detect: LiveDetect | None,
    ) -> None:
        self.hub, self.scenes, self.live_map, self.live_detect = hub, scenes, live_map, live_detect

    async def on_stored(self, robot: str, message: Message, result: StoreResult) -> None:
        """Called after each stored message's ACK (``robot``: the sender's name)."""
        self.show(robot, message)
        sid, new = str(message.session_id), result.status == "stored"
        if self.live_map is not None and message.type is MessageType.SESSION_START:
            self.live_map.warm()
        if self.live_map is not None and message.type is MessageType.CLOUD and new:
            self.live_map.offer(sid, message.payload, message.meta, message.timestamp)
        if self.live_map is not None and message.type is MessageType.FRAME and new:
            self.live_map.offer_frame(sid, message.payload, message.meta, message.timestamp)
        if self.live_detect is not None and message.type is MessageType.FRAME and new:
            self.live_detect.offer(sid, message.seq, message.payload, message.meta)

    def show_live(self, message: Message) -> None:
        """A message that is live only, never stored: a VIDEO preview frame, or a robot's
        answer to a command (COMMAND_ACK)."""
        sid = str(message.session_id)
        if message.type is MessageType.VIDEO:
            header = FrameHeader(session_id=sid, seq=message.seq, t=message.timestamp, video=True)
            self.hub.publish_frame(header, message.payload)
        elif message.type is MessageType.COMMAND_ACK:
            fields = {k: v for k, v in message.meta.items() if k not in ("type", "seq")}
            self.hub.publish(CommandAck(**fields, session_id=sid, seq=message.seq))

    def show(self, robot: str, message: Message) -> None:
        """Show the message to watching browsers (and the robot's pose in the 3D view)."""
        sid = str(message.session_id)
        pose = message.meta.get("pose")
        if (
            self.scenes is not None
            and isinstance(pose, dict)
            and message.type in (MessageType.FRAME, MessageType.TELEMETRY)
        ):
            self.scenes.live.show_pose(
                sid, float(pose["x"]), float(pose["y"]), float(pose["yaw"]), robot
            )
        if message.type is MessageType.FRAME:
            header = FrameHeader(
                session_id=sid, seq=message.seq, t=message.timestamp, pose=message.meta.get("pose")
            )
            self.hub.publish_frame(header, message.payload)
        elif message.type is MessageType.TELEMETRY:
            data = {**message.meta, "t": message.timestamp}
            self.hub.publish(Telemetry(session_id=sid, data=data))
        elif message.type in (MessageType.SESSION_START, MessageType.SESSION_END):
            event = "session_start" if message.type is MessageType.SESSION_START else "session_end"
            self.hub.publish(Session(session_id=sid, event=event, robot=robot))
