"""ToF adapters behind one interface: an Intel RealSense depth camera (``pyrealsense2``), a
replay of organised clouds (a folder of .ply/.pcd with ``sensor.json``), and the MCU
emulator's simulated ToF. Each gives a depth image in metres (NaN: no return) and the
pinhole intrinsics it was taken with."""

from __future__ import annotations

import asyncio
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from robot_link.agent.config import TofConfig
from robot_link.agent.emulator_sensors import EmulatorSensors

CLOUD_SUFFIXES = {".ply", ".pcd"}


class TofError(RuntimeError):
    """The depth camera gave no depth image."""


@dataclass(frozen=True)
class Depth:
    """A depth image (H, W) in metres, the monotonic time of its exposure."""

    depth_m: NDArray[np.float32]
    t: float


class TofSource(Protocol):
    """What the agent needs of a ToF camera."""

    name: str
    intrinsics: dict[str, float]  # width, height, fx, fy, cx, cy

    async def open(self) -> None:
        """Open the device; TofError if it cannot be."""

    async def grab(self) -> Depth:
        """The next depth image."""

    async def close(self) -> None:
        """Release the device."""


class RealSenseTof:
    """An Intel RealSense depth camera through its PyPI library."""

    def __init__(self, config: TofConfig, width: int = 640, height: int = 480) -> None:
        self.name = "RealSense"
        self.size = (width, height)
        self.intrinsics: dict[str, float] = {}
        self._pipe: Any = None
        self._scale = 0.001

    async def open(self) -> None:
        """Start the depth stream."""
        try:
            import pyrealsense2 as rs
        except ImportError:
            raise TofError(
                'tof source "realsense" needs pyrealsense2: pip install "steelscan[realsense]"'
            ) from None
        try:
            pipe = rs.pipeline()
            cfg = rs.config()
            cfg.enable_stream(rs.stream.depth, *self.size, rs.format.z16, 30)
            profile = pipe.start(cfg)
        except RuntimeError as exc:
            raise TofError(f"no RealSense camera: {exc}") from None
        self._scale = profile.get_device().first_depth_sensor().get_depth_scale()
        intr = profile.get_stream(rs.stream.depth).as_video_stream_profile().get_intrinsics()
        self.intrinsics = {
            "width": intr.width,
            "height": intr.height,
            "fx": intr.fx,
            "fy": intr.fy,
            "cx": intr.ppx,
            "cy": intr.ppy,
        }
        self._pipe = pipe

    async def grab(self) -> Depth:
        """The next depth frame in metres."""
        if self._pipe is None:
            raise TofError("the RealSense is not open")
        t = time.monotonic()
        try:
            frames = await asyncio.to_thread(self._pipe.wait_for_frames, 1000)
        except RuntimeError as exc:
            raise TofError(f"the RealSense gave no frame: {exc}") from None
        raw = np.asanyarray(frames.get_depth_frame().get_data()).astype(np.float32)
        depth = raw * self._scale
        depth[raw == 0] = np.nan
        return Depth(depth, t)

    async def close(self) -> None:
        """Stop the stream."""
        if self._pipe is not None:
            self._pipe.stop()
            self._pipe = None


class ReplayTof:
    """Organised clouds (x right, y down, z forward; NaN where no return) of a folder with
    ``sensor.json``, one per grab, starting again after the last."""

    def __init__(self, config: TofConfig) -> None:
        self.folder = Path(config.source)
        self.name = f"ToF replay {self.folder}"
        self.intrinsics: dict[str, float] = {}
        self._files: list[Path] = []
        self._next = 0

    async def open(self) -> None:
        """Read sensor.json and list the clouds."""
        try:
            sensor = json.loads((self.folder / "sensor.json").read_text())
            self.intrinsics = {k: sensor[k] for k in ("width", "height", "fx", "fy", "cx", "cy")}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise TofError(f"{self.folder}: no usable sensor.json ({exc})") from None
        self._files = sorted(p for p in self.folder.iterdir() if p.suffix.lower() in CLOUD_SUFFIXES)
        if not self._files:
            raise TofError(f"{self.folder} holds no .ply or .pcd clouds")

    async def grab(self) -> Depth:
        """The next cloud as a depth image."""
        t = time.monotonic()
        path = self._files[self._next % len(self._files)]
        self._next += 1
        return Depth(await asyncio.to_thread(self._depth, path), t)

    def _depth(self, path: Path) -> NDArray[np.float32]:
        import open3d as o3d

        pcd = o3d.io.read_point_cloud(path, remove_nan_points=False, remove_infinite_points=False)
        pts = np.asarray(pcd.points, np.float32)
        w, h = int(self.intrinsics["width"]), int(self.intrinsics["height"])
        if len(pts) != w * h:
            raise TofError(f"{path}: {len(pts)} points, but sensor.json says {w}x{h}")
        return np.ascontiguousarray(pts[:, 2].reshape(h, w))

    async def close(self) -> None:
        """Nothing to release."""


class EmulatorTof:
    """The MCU emulator's simulated ToF camera."""

    def __init__(self, sensors: EmulatorSensors, intrinsics: dict[str, float]) -> None:
        self.sensors = sensors
        self.name = "emulator ToF"
        self.intrinsics = intrinsics

    async def open(self) -> None:
        """Nothing to open."""

    async def grab(self) -> Depth:
        """The simulated depth at the robot's true pose now."""
        t = time.monotonic()
        try:
            depth, _ = await self.sensors.request("tof")
        except OSError as exc:
            raise TofError(str(exc)) from None
        return Depth(depth.astype(np.float32, copy=False), t)

    async def close(self) -> None:
        """Nothing to release."""


def tof_source(
    config: TofConfig, sensors: EmulatorSensors | None, emulator_info: dict[str, Any]
) -> TofSource:
    """The adapter for ``config.source``."""
    if config.source == "emulator":
        if sensors is None or "tof" not in emulator_info:
            raise TofError('tof source "emulator" needs an MCU emulator on the serial line')
        intr = {k: emulator_info["tof"][k] for k in ("width", "height", "fx", "fy", "cx", "cy")}
        return EmulatorTof(sensors, intr)
    if config.source == "realsense":
        return RealSenseTof(config)
    return ReplayTof(config)
