"""The client side of the MCU emulator's sensor socket (:mod:`robot_link.emulator.sensor_server`):
the camera and ToF images of the emulated robot."""

from __future__ import annotations

import asyncio
import json

import numpy as np
from numpy.typing import NDArray


class EmulatorSensors:
    """One connection to the emulator's sensor socket, shared by the camera and the ToF;
    requests take turns."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._streams: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        self._lock = asyncio.Lock()

    async def request(
        self, sensor: str, *, exact: bool = True
    ) -> tuple[NDArray[np.generic], float]:
        """The sensor's image now and the emulator's clock at its exposure."""
        async with self._lock:
            try:
                return await self._request(sensor, exact)
            except (OSError, asyncio.IncompleteReadError, ValueError) as exc:
                await self.close()
                raise OSError(f"the emulator's {sensor} at {self.path}: {exc}") from None

    async def _request(self, sensor: str, exact: bool) -> tuple[NDArray[np.generic], float]:
        if self._streams is None:
            self._streams = await asyncio.open_unix_connection(self.path, limit=2**20)
        reader, writer = self._streams
        writer.write(json.dumps({"sensor": sensor, "exact": exact}).encode() + b"\n")
        await writer.drain()
        head = json.loads(await reader.readline())
        if "error" in head:
            raise ValueError(head["error"])
        shape = tuple(int(v) for v in head["shape"])
        dtype = np.dtype(head["dtype"])
        data = await reader.readexactly(int(np.prod(shape)) * dtype.itemsize)
        return np.frombuffer(data, dtype).reshape(shape).copy(), float(head["t"])

    async def close(self) -> None:
        """Close the connection (a later request opens it again)."""
        if self._streams is not None:
            self._streams[1].close()
            self._streams = None
