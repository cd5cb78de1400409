"""The on-board link client's own rules, without a station."""

import asyncio
import time
import uuid

from robot_link.client import RobotLink
from robot_link.protocol import Message, MessageType


def test_commands_are_never_acted_on_twice_but_stopping_always_is() -> None:
    obeyed: list[tuple[int, str]] = []

    async def run() -> None:
        link = RobotLink("http://127.0.0.1:1", "token", on_command=lambda m: obeyed.append((m.seq, m.meta["cmd"])))
        sid = uuid.uuid4()

        def command(seq: int, cmd: str) -> Message:
            return Message(MessageType.COMMAND, sid, seq, time.time(), {"cmd": cmd, "args": {}})

        for seq, cmd in [(10, "resume"), (11, "capture"), (10, "resume"), (5, "capture"), (7, "estop"), (12, "resume")]:
            await link._handle(command(seq, cmd))

    asyncio.run(run())
    assert obeyed == [(10, "resume"), (11, "capture"), (7, "estop"), (12, "resume")]
