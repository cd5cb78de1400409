"""The host side of the serial link against the MCU emulator on a real pseudo-terminal:
handshake, commands reaching the emulated wheels, a silent and a garbled line noticed (and
their recovery), a missing device and a silent MCU refused at the start."""

from __future__ import annotations

import asyncio
import signal
import time

import pytest

from robot_link.emulator.process import EmulatorProcess
from robot_link.mcu.link import McuError, McuLink
from robot_link.mcu.packets import PacketType


def test_handshake_and_the_wheels_obey_drive_commands(emulator: EmulatorProcess) -> None:
    async def main() -> None:
        samples = []
        link = McuLink(emulator.device, on_sensors=samples.append)
        reply = await link.open()
        assert reply.version == 1 and reply.sensor_hz == 50
        assert reply.info["robot"]["track_m"] > 0
        start = emulator.latest()
        for _ in range(40):  # 0.8 s at 0.1 m/s
            link.drive(0.1, 0.1, 0.2)
            await asyncio.sleep(0.02)
        moved = emulator.wait_for(lambda s: s["speed"] > 0.09, 2.0)
        assert moved["x"] != start["x"] or moved["y"] != start["y"]
        assert samples and samples[-1].hall[0] > samples[0].hall[0]
        ack = await link.request(PacketType.STOP)
        assert ack.status == 0
        await link.close()

    asyncio.run(main())
    emulator.wait_for(lambda s: s["speed"] == 0.0, 2.0)


def test_the_mcu_stops_by_itself_when_drive_commands_stop(emulator: EmulatorProcess) -> None:
    async def main() -> None:
        link = McuLink(emulator.device)
        await link.open()
        for _ in range(20):
            link.drive(0.1, 0.1, 5.0)  # asks for 5 s: the firmware holds 0.2 s at most
            await asyncio.sleep(0.02)
        await asyncio.sleep(0.6)
        await link.close()

    asyncio.run(main())
    moving = [s for _, s in emulator.states if s["speed"] > 0]
    assert moving
    last_drive = moving[-1]["last_drive_t"]
    stopped = next(s for _, s in emulator.states if s["t"] > last_drive and s["speed"] == 0)
    assert stopped["t"] - last_drive <= 0.2 + 0.1 + 0.1  # hold, ramp down, state period


@pytest.mark.parametrize("sig,words", [(signal.SIGUSR1, "silent"), (signal.SIGUSR2, "garbled")])
def test_a_silent_or_garbled_line_is_a_fault_until_it_recovers(
    emulator: EmulatorProcess, sig: int, words: str
) -> None:
    async def main() -> list[str | None]:
        faults: list[str | None] = []
        link = McuLink(emulator.device, on_fault=faults.append)
        await link.open()
        emulator.signal(sig)
        for _ in range(50):
            await asyncio.sleep(0.05)
            if faults:
                break
        assert not link.ok
        emulator.signal(sig)
        for _ in range(50):
            await asyncio.sleep(0.05)
            if link.ok:
                break
        await link.close()
        return faults

    faults = asyncio.run(main())
    assert faults[0] is not None and words in faults[0]
    assert faults[-1] is None  # healthy again


def test_a_missing_device_or_a_silent_mcu_fails_the_start(emulator: EmulatorProcess) -> None:
    async def open_(device: str) -> None:
        await McuLink(device).open(timeout_s=0.5)

    with pytest.raises(McuError, match="cannot open"):
        asyncio.run(open_("/dev/does-not-exist"))
    emulator.signal(signal.SIGUSR1)
    time.sleep(0.3)  # the emulator's loop takes the signal within a tick
    with pytest.raises(McuError, match="did not answer"):
        asyncio.run(open_(emulator.device))
