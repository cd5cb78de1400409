"""The emulated robot's camera and ToF, served over a Unix socket to an on-board agent whose
config says ``source = "emulator"`` (the socket's path comes in the MCU's HELLO reply).

A request is one JSON line, ``{"sensor": "camera", "exact": true}`` or
``{"sensor": "tof"}``; the answer is one JSON line (``shape``, ``dtype``, ``t``: the
emulator's clock at the exposure) followed by the raw array bytes. Images are rendered at
the robot's true pose when the request arrives.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from functools import partial
from typing import Any

import numpy as np

from robot_link.emulator.firmware import Firmware


class SensorServer:
    """Answers camera and ToF requests from the firmware's world."""

    def __init__(self, firmware: Firmware, path: str) -> None:
        self.firmware = firmware
        self.path = path
        self.rng = np.random.default_rng(firmware.world.seed + 7)
        self._server: asyncio.Server | None = None

    async def start(self) -> None:
        """Listen on the socket path."""
        self._server = await asyncio.start_unix_server(self._serve, path=self.path)

    async def close(self) -> None:
        """Stop listening."""
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await self._server.wait_closed()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while line := await reader.readline():
                try:
                    request = json.loads(line)
                    array, t = await self._render(request)
                except (ValueError, KeyError, TypeError) as exc:
                    writer.write(json.dumps({"error": str(exc)}).encode() + b"\n")
                    await writer.drain()
                    continue
                head = {"shape": list(array.shape), "dtype": str(array.dtype), "t": t}
                writer.write(json.dumps(head).encode() + b"\n")
                writer.write(np.ascontiguousarray(array).tobytes())
                await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()

    async def _render(self, request: dict[str, Any]) -> tuple[np.ndarray, float]:
        world = self.firmware.world
        pose = world.robot.pose.copy()
        t = self.firmware.t_s
        sensor = request["sensor"]
        if sensor == "camera":
            cam = world.camera.pose_in_world(pose)
            render = partial(world.camera.render, exact=bool(request.get("exact", True)))
            image = await asyncio.to_thread(render, world.structure, cam, self.rng)
            return image, t
        if sensor == "tof":
            T = world.tof.T_world_tof(pose)
            depth = await asyncio.to_thread(world.tof.render, T, self.rng)
            return depth, t
        raise ValueError(f"unknown sensor {sensor!r}: camera or tof")
