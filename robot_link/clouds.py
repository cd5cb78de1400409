"""Compact binary encodings of ToF point clouds for the wire (depth PNG or raw float32 xyz)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from robot_link.image_header import ImageHeaderError, png_header
from robot_link.protocol import ProtocolError

MAX_DEPTH_MM = 65535


def encode_depth_png(depth_m: NDArray[np.floating]) -> bytes:
    """Encode an (H, W) depth image in metres (NaN = no return) as a 16-bit PNG in mm."""
    if depth_m.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth_m.shape}")
    mm = np.where(np.isfinite(depth_m), np.round(depth_m * 1000.0), 0)
    mm = np.clip(mm, 0, MAX_DEPTH_MM).astype(np.uint16)
    ok, buf = cv2.imencode(".png", mm)
    if not ok:
        raise ValueError("could not encode the depth image as PNG")
    return buf.tobytes()


def decode_depth_png(payload: bytes, width: int, height: int) -> NDArray[np.float32]:
    """Decode a 16-bit depth PNG (mm) to an (H, W) float32 image in metres, NaN where 0.

    The PNG's header is checked first: one declaring another size is refused before its
    pixels are allocated (a decompression bomb)."""
    try:
        png = png_header(payload)
    except ImageHeaderError as exc:
        raise ProtocolError(f"depth image: {exc}") from None
    if (png.width, png.height) != (width, height):
        raise ProtocolError(f"depth PNG is {png.width}×{png.height}, expected {width}×{height}")
    arr = cv2.imdecode(np.frombuffer(payload, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None or arr.dtype != np.uint16 or arr.shape != (height, width):
        got = "undecodable" if arr is None else f"{arr.dtype} {arr.shape}"
        raise ProtocolError(f"depth PNG must be uint16 ({height}, {width}), got {got}")
    depth = arr.astype(np.float32) / 1000.0
    depth[arr == 0] = np.nan
    return depth


def depth_to_points(
    depth_m: NDArray[np.floating], fx: float, fy: float, cx: float, cy: float
) -> NDArray[np.float32]:
    """Back-project an (H, W) depth image to an organized (H*W, 3) cloud in the sensor frame."""
    h, w = depth_m.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    z = depth_m.astype(np.float32)
    pts = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=-1)
    return pts.reshape(-1, 3)


def encode_xyz(points: NDArray[np.floating]) -> bytes:
    """Encode an (N, 3) cloud as little-endian float32 triples."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got shape {points.shape}")
    return np.ascontiguousarray(points, dtype="<f4").tobytes()


def decode_xyz(payload: bytes, count: int) -> NDArray[np.float32]:
    """Decode ``count`` float32 xyz triples."""
    if len(payload) != count * 12:
        raise ProtocolError(f"xyz payload is {len(payload)} bytes, expected {count * 12}")
    return np.frombuffer(payload, dtype="<f4").reshape(count, 3).astype(np.float32)


def decode_cloud(payload: bytes, meta: dict[str, Any]) -> NDArray[np.float32]:
    """Decode a CLOUD message's payload to an (N, 3) float32 array (NaN rows = no return)."""
    if meta["encoding"] == "png16_depth_mm":
        depth = decode_depth_png(payload, meta["width"], meta["height"])
        return depth_to_points(depth, meta["fx"], meta["fy"], meta["cx"], meta["cy"])
    return decode_xyz(payload, meta["width"] * meta["height"])
