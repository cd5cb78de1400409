"""Run the simulated inspection offline, keeping what the robot would send (for benchmarks)."""

from __future__ import annotations

import asyncio
import uuid
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robot_link.client import LinkStats
from robot_link.protocol import Message, MessageType
from robot_link.sim.inspection import InspectionSim, SimConfig, SimResult


class RecordingLink:
    """Stands in for :class:`robot_link.client.RobotLink`: keeps messages instead of sending."""

    def __init__(self) -> None:
        self.session_id = uuid.uuid4()
        self.stats = LinkStats()
        self.pending = 0
        self.on_command: Any = None
        self.messages: list[Message] = []

    async def send(self, mtype: MessageType, meta: dict[str, Any] | None = None, payload: bytes = b"") -> int:
        """Keep the message; returns its seq."""
        seq = len(self.messages) + 1
        self.messages.append(Message(mtype, self.session_id, seq, 0.0, meta or {}, payload))
        return seq

    async def notify(self, mtype: MessageType, meta: dict[str, Any], *, seq: int) -> None:
        """Nothing to notify offline."""

    async def flush(self, timeout_s: float = 0.0) -> None:
        """Everything is 'acknowledged' at once."""


@dataclass
class Recording:
    """Frames (JPEG bytes) with odometry and true camera poses, clouds with poses, truth."""

    frames: list[bytes] = field(default_factory=list)
    frame_odometry: list[dict[str, float]] = field(default_factory=list)
    frame_truth: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    cloud_messages: list[Message] = field(default_factory=list)
    calibration: dict[str, Any] = field(default_factory=dict)
    result: SimResult | None = None


def record_inspection(config: SimConfig) -> Recording:
    """Run one inspection route offline (as fast as possible) and return what was sent."""
    link = RecordingLink()
    sim = InspectionSim(link, SimConfig(**{**config.__dict__, "time_scale": 0.0}))  # type: ignore[arg-type]
    result = asyncio.run(sim.run())
    rec = Recording(calibration=sim.calibration(), result=result)
    for m in link.messages:
        if m.type is MessageType.FRAME:
            rec.frames.append(m.payload)
            rec.frame_odometry.append(m.meta["pose"])
        elif m.type is MessageType.CLOUD:
            rec.cloud_messages.append(m)
    rec.frame_truth = np.array(result.frame_poses_true)
    return rec
