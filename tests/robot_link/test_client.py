"""The on-board link client's own rules, and what the robot does when its link drops (through a
proxy that cuts it)."""

import asyncio
import time
import uuid

from robot_link.client import RobotLink
from robot_link.protocol import Message, MessageType


def test_commands_are_never_acted_on_twice_but_stopping_always_is() -> None:
    obeyed: list[tuple[int, str]] = []

    async def run() -> None:
        link = RobotLink(
            "http://127.0.0.1:1",
            "token",
            on_command=lambda m: obeyed.append((m.seq, m.meta["cmd"])),
        )
        sid = uuid.uuid4()

        def command(seq: int, cmd: str) -> Message:
            return Message(MessageType.COMMAND, sid, seq, time.time(), {"cmd": cmd, "args": {}})

        for seq, cmd in [
            (10, "resume"),
            (11, "capture"),
            (10, "resume"),
            (5, "capture"),
            (7, "estop"),
            (12, "resume"),
        ]:
            await link._handle(command(seq, cmd))

    asyncio.run(run())
    assert obeyed == [(10, "resume"), (11, "capture"), (7, "estop"), (12, "resume")]


def test_the_robot_stops_the_moment_its_link_drops_and_drives_again_only_when_told(
    live_server,
) -> None:  # type: ignore[no-untyped-def]
    from robot_link.sim.teleop import TeleopSim
    from tests.fault_proxy import FaultProxy

    port = int(live_server.url.rsplit(":", 1)[1])
    changes: list[bool] = []

    async def run() -> float:
        proxy = FaultProxy(port, cut_probability=0.0, stall_probability=0.0, delay_s=(0.0, 0.0))
        proxy_port = await proxy.start()
        link = RobotLink(f"http://127.0.0.1:{proxy_port}", live_server.token, max_backoff_s=0.2)
        sim = TeleopSim(link)
        stop_on_drop = link.on_link_change
        assert stop_on_drop is not None

        def record(up: bool) -> None:
            changes.append(up)
            stop_on_drop(up)

        link.on_link_change = record
        await link.start()
        try:
            await link.send(MessageType.SESSION_START, {"structure": "link drop"})
            await link.flush(timeout_s=10)
            sim.v, sim.w = 0.1, 0.2  # driving
            t0 = time.monotonic()
            proxy.cut_all()
            while sim.v != 0.0 and time.monotonic() - t0 < 2:
                await asyncio.sleep(0.002)
            stopped_after = time.monotonic() - t0
            # it reconnects by itself ...
            while changes[-1] is not True and time.monotonic() - t0 < 10:
                await asyncio.sleep(0.01)
            assert sim.v == 0.0 and sim.w == 0.0  # ... and stays stopped until commanded
        finally:
            await link.close()
            await proxy.stop()
        return stopped_after

    stopped_after = asyncio.run(run())
    assert stopped_after < 0.1  # at once, not after the dead-man bound (0.3 s)
    assert changes[:3] == [True, False, True]
