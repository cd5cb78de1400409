"""Camera adapters: a V4L2 camera or video file through OpenCV's ``VideoCapture``, a folder
of images (replays, tests), and the MCU emulator's simulated camera. All give BGR frames
with the monotonic time of their exposure, undistorted when the config has a calibration."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from robot_link.agent.config import CameraConfig
from robot_link.agent.emulator_sensors import EmulatorSensors

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}


class CameraError(RuntimeError):
    """The camera gave no frame (unplugged, wrong device, unreadable file)."""


@dataclass(frozen=True)
class Grab:
    """One frame and the monotonic time of its exposure."""

    image: NDArray[np.uint8]
    t: float


class CameraSource(Protocol):
    """What the agent needs of a camera."""

    name: str

    async def open(self) -> None:
        """Open the device; CameraError if it cannot be."""

    async def grab(self, *, exact: bool = True) -> Grab:
        """The next frame (``exact``: full quality, for inspection; else a preview)."""

    async def close(self) -> None:
        """Release the device."""


class OpenCVCamera:
    """A V4L2 camera (index or /dev/videoN) or a video file through OpenCV, with exposure and
    gain locked (a mosaic needs constant brightness) and the lens calibration applied."""

    def __init__(self, config: CameraConfig) -> None:
        self.config = config
        self.name = f"camera {config.source}"
        self._cap: cv2.VideoCapture | None = None
        self._maps: tuple[NDArray[np.int16], NDArray[np.uint16]] | None = None
        self._file = isinstance(config.source, str) and Path(config.source).is_file()

    async def open(self) -> None:
        """Open and configure the device."""
        await asyncio.to_thread(self._open)

    def _open(self) -> None:
        src = self.config.source
        if isinstance(src, str) and src.isdigit():
            src = int(src)
        if self._file:
            cap = cv2.VideoCapture(str(src))
        else:
            cap = cv2.VideoCapture(src, cv2.CAP_V4L2)
        if not cap.isOpened():
            raise CameraError(f"cannot open the camera {self.config.source}")
        if not self._file:
            c = self.config
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, c.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, c.height)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
            if c.exposure is not None:
                cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: 1 = manual
                cap.set(cv2.CAP_PROP_EXPOSURE, c.exposure)
            if c.gain is not None:
                cap.set(cv2.CAP_PROP_GAIN, c.gain)
            cap.set(cv2.CAP_PROP_AUTO_WB, 0)
        self._cap = cap

    async def grab(self, *, exact: bool = True) -> Grab:
        """The next frame, undistorted."""
        if self._cap is None:
            raise CameraError(f"{self.name} is not open")
        t = time.monotonic()
        ok, image = await asyncio.to_thread(self._cap.read)
        if not ok and self._file:  # a replayed video starts again
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, image = await asyncio.to_thread(self._cap.read)
        if not ok or image is None:
            await self.close()
            raise CameraError(f"{self.name} gave no frame (unplugged?)")
        return Grab(undistort(np.asarray(image, np.uint8), self.config, self), t)

    async def close(self) -> None:
        """Release the device."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class FolderCamera:
    """Images of a folder in name order, one per grab, starting again after the last."""

    def __init__(self, config: CameraConfig) -> None:
        self.config = config
        self.name = f"image folder {config.source}"
        self.folder = Path(str(config.source))
        self._files: list[Path] = []
        self._next = 0

    async def open(self) -> None:
        """List the folder's images."""
        if not self.folder.is_dir():
            raise CameraError(f"{self.folder} is not a folder of images")
        self._files = sorted(p for p in self.folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self._files:
            raise CameraError(f"{self.folder} holds no images")

    async def grab(self, *, exact: bool = True) -> Grab:
        """The next image."""
        t = time.monotonic()
        path = self._files[self._next % len(self._files)]
        self._next += 1
        image = await asyncio.to_thread(cv2.imread, str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise CameraError(f"cannot read the image {path}")
        return Grab(np.asarray(image, np.uint8), t)

    async def close(self) -> None:
        """Nothing to release."""


class EmulatorCamera:
    """The MCU emulator's simulated downward camera."""

    def __init__(self, sensors: EmulatorSensors) -> None:
        self.sensors = sensors
        self.name = "emulator camera"

    async def open(self) -> None:
        """Nothing to open: the socket connects on the first grab."""

    async def grab(self, *, exact: bool = True) -> Grab:
        """The simulated image at the robot's true pose now."""
        t = time.monotonic()
        try:
            image, _ = await self.sensors.request("camera", exact=exact)
        except OSError as exc:
            raise CameraError(str(exc)) from None
        return Grab(image.astype(np.uint8, copy=False), t)

    async def close(self) -> None:
        """Nothing to release (the shared socket closes with the agent)."""


def undistort(image: NDArray[np.uint8], config: CameraConfig, cache: object) -> NDArray[np.uint8]:
    """``image`` with the lens distortion of ``config`` removed (unchanged without one);
    the remap tables are kept on ``cache``."""
    if config.camera_matrix is None or config.distortion is None:
        return image
    maps = getattr(cache, "_maps", None)
    h, w = image.shape[:2]
    if maps is None or maps[0].shape[:2] != (h, w):
        K = np.asarray(config.camera_matrix, np.float64)
        dist = np.asarray(config.distortion, np.float64)
        maps = cv2.initUndistortRectifyMap(K, dist, None, K, (w, h), cv2.CV_16SC2)
        setattr(cache, "_maps", maps)
    return np.asarray(cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR), np.uint8)


def camera_source(config: CameraConfig, sensors: EmulatorSensors | None) -> CameraSource:
    """The adapter for ``config.source``."""
    src = config.source
    if src == "emulator":
        if sensors is None:
            raise CameraError('camera source "emulator" needs an MCU emulator on the serial line')
        return EmulatorCamera(sensors)
    if isinstance(src, str) and Path(src).is_dir():
        return FolderCamera(config)
    return OpenCVCamera(config)
