"""``steelscan mcu-emulator``: the firmware on a pseudo-terminal, in real time.

Prints ``pty: PATH``, then a header line (plate, robot outline, camera footprint), then the
robot's true state as one JSON line every 0.1 s. SIGUSR1 makes the MCU fall silent (or
speak again), SIGUSR2 garbles its frames (or stops garbling): faults a test can inject.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import sys
import tempfile
import time
import tty
from typing import TextIO

import numpy as np

from robot_link.emulator.firmware import Firmware
from robot_link.emulator.sensor_server import SensorServer
from robot_link.emulator.world import OUTLINE_M, World
from robot_link.mcu.framing import Frame, FrameError, FrameReader, encode_frame
from robot_link.mcu.packets import PacketType

TICK_S = 0.01
STATE_S = 0.1


class Emulator:
    """The MCU on the master side of a pty; the agent opens the slave as its serial port."""

    def __init__(self, world: World, out: TextIO = sys.stdout) -> None:
        self.world = world
        self.out = out
        self.firmware = Firmware(world)
        self.folder = tempfile.mkdtemp(prefix="steelscan-mcu-")
        self.sensors = SensorServer(self.firmware, os.path.join(self.folder, "sensors.sock"))
        self.firmware.info = self._info()
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.silent = False
        self.garble = False
        self._reader = FrameReader()
        self._seq = 0
        self._stop = asyncio.Event()

    def _info(self) -> dict[str, object]:
        w = self.world
        cam = w.camera
        return {
            "firmware": "steelscan-mcu-emulator 1.0",
            "robot": {
                "track_m": w.spec.track_m,
                "wheelbase_m": w.spec.wheelbase_m,
                "wheel_radius_m": w.spec.wheel_radius_m,
                "edges_per_wheel_turn": 4 * w.spec.magnets_per_wheel,
                "ir_positions_m": [list(p) for p in w.spec.ir_corners_m],
                "ir_calibrated_m": w.spec.ir_calibrated_m,
                "outline_m": list(OUTLINE_M),
            },
            "emulator": {
                "sensors": self.sensors.path,
                "camera": {
                    "width": cam.width,
                    "height": cam.height,
                    "px_per_m": 1.0 / cam.m_per_px,
                    "mount_x_m": cam.mount_x_m,
                },
                "tof": {**w.tof.intrinsics(), "T_robot_tof": w.tof.T_robot_tof.tolist()},
                "inclination_deg": w.inclination_deg,
            },
        }

    def _line(self, obj: object) -> None:
        try:
            self.out.write(json.dumps(obj) + "\n")
            self.out.flush()
        except (BrokenPipeError, ValueError):  # nobody reads the states any more: stop
            self._stop.set()

    async def run(self) -> None:
        """Serve until SIGTERM/SIGINT."""
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self._stop.set)
        loop.add_signal_handler(signal.SIGUSR1, self._toggle_silent)
        loop.add_signal_handler(signal.SIGUSR2, self._toggle_garble)
        await self.sensors.start()
        self.out.write(f"pty: {self.path}\n")
        self._line(self.world.header())
        loop.add_reader(self.master, self._readable)
        try:
            await self._loop()
        finally:
            loop.remove_reader(self.master)
            await self.sensors.close()
            with contextlib.suppress(OSError):
                os.close(self.master)
                os.close(self.slave)
            with contextlib.suppress(OSError):
                os.unlink(self.sensors.path)
                os.rmdir(self.folder)

    def _toggle_silent(self) -> None:
        self.silent = not self.silent

    def _toggle_garble(self) -> None:
        self.garble = not self.garble

    async def _loop(self) -> None:
        t0 = time.monotonic()
        ticks = 0
        per_sensor = round(1.0 / (self.firmware.params.sensor_hz * TICK_S))
        per_state = round(STATE_S / TICK_S)
        while not self._stop.is_set():
            self.firmware.tick(TICK_S)
            ticks += 1
            if ticks % per_sensor == 0:
                self._send(PacketType.SENSORS, self.firmware.sensors().pack())
            if ticks % per_state == 0:
                self._line(self.state())
            delay = t0 + ticks * TICK_S - time.monotonic()
            if delay < -1.0:  # far behind (a stalled machine): do not race to catch up
                t0, ticks = time.monotonic(), 0
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), max(0.0, delay))

    def state(self) -> dict[str, object]:
        """The robot's true state: the header's contract fields and the firmware's flags."""
        x, y, heading = (float(v) for v in self.world.robot.pose)
        fw = self.firmware
        return {
            "t": round(fw.t_s, 3),
            "x": round(x, 5),
            "y": round(y, 5),
            "heading": round(heading, 5),
            "speed": round((fw.wheels[0] + fw.wheels[1]) / 2, 5),
            "on_plate": self.world.wheels_on_plate(),
            "estop": fw.estop,
            "flags": int(fw.flags),
            "faults": int(fw.faults),
            "last_drive_t": None if fw.last_drive_t is None else round(fw.last_drive_t, 3),
        }

    def _readable(self) -> None:
        try:
            data = os.read(self.master, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""  # the agent closed the port: wait for the next one
        for item in self._reader.feed(data):
            if isinstance(item, FrameError):
                self.firmware.host_garbled += 1
            elif not self.silent:
                self._answer(item)

    def _answer(self, frame: Frame) -> None:
        ptype, body = self.firmware.handle(frame.type, frame.seq, frame.body)
        self._send(ptype, body)

    def _send(self, ptype: PacketType, body: bytes) -> None:
        if self.silent:
            return
        self._seq = (self._seq + 1) & 0xFF
        data = encode_frame(ptype, self._seq, body)
        if self.garble:
            damaged = bytearray(data)
            damaged[len(damaged) // 2] ^= 0x5A
            data = bytes(damaged)
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self.master, data)


def run_emulator(world: World, out: TextIO = sys.stdout) -> None:
    """Run the emulator until it is signalled to stop."""
    np.seterr(all="ignore")
    asyncio.run(Emulator(world, out).run())
