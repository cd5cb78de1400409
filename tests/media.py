"""Small real images for tests: a JPEG and a 16-bit depth PNG of a given size."""

from __future__ import annotations

import cv2
import numpy as np

from robot_link.clouds import encode_depth_png


def jpeg(width: int = 640, height: int = 480) -> bytes:
    """A grey-gradient JPEG of this size (bytes appended to it keep it readable)."""
    ramp = np.linspace(40, 200, width, dtype=np.float32)
    image = np.repeat(ramp[None, :], height, axis=0).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 80])
    assert ok
    return buf.tobytes()


def undecodable_jpeg(width: int = 640, height: int = 480) -> bytes:
    """A JPEG whose header is sound (size and all) and which has no image data."""
    data = jpeg(width, height)
    sof = data.index(b"\xff\xc0")
    return data[: sof + 2 + int.from_bytes(data[sof + 2 : sof + 4], "big")]


def depth_png(width: int, height: int, metres: float = 0.5) -> bytes:
    """A flat depth image of this size as the protocol's 16-bit PNG in millimetres."""
    return encode_depth_png(np.full((height, width), metres, np.float32))
