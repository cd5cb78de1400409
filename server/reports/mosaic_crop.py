"""A session's mosaic cut to a rectangle of its structure: the pixels that show a box given
in the structure's frame, placed through the session's datum, resampled so that every
visit's crop of one box covers the same ground at the same size (for comparing visits).

Mosaic pixel (u, v) is at ``origin_m + (u, v) / px_per_m`` in the session's world frame;
the datum (x, y, yaw) is that frame's pose in the structure's."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.poses import se2_matrix
from server.storage.mosaic_files import read_region

Box = tuple[float, float, float, float]  # x0, y0, x1, y1 in the structure's frame (m)
MAX_SOURCE_PX = 4096 * 4096  # full-resolution pixels read for one crop at most


def crop_affine(
    box: Box,
    size_px: int,
    datum: dict[str, Any] | None,
    origin_m: tuple[float, float],
    px_per_m: float,
) -> tuple[NDArray[np.float64], tuple[int, int]]:
    """The 2×3 affine map from a crop's pixels to mosaic pixels, and the crop's (width,
    height): ``box`` at ``size_px`` along its longer side, crop pixel (i, j) showing
    structure point ``(x0, y0) + (i, j) * side / size_px``; the mosaic of ``px_per_m``
    pixels per metre with pixel (0, 0) at ``origin_m`` in the session's world frame, whose
    pose on the structure is ``datum``."""
    x0, y0, x1, y1 = box
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"box must have x0 < x1 and y0 < y1, got {box}")
    if size_px < 1 or px_per_m <= 0:
        raise ValueError(f"size_px and px_per_m must be positive, got {size_px}, {px_per_m}")
    crop_per_m = size_px / max(x1 - x0, y1 - y0)
    if not np.isfinite(crop_per_m):
        raise ValueError(f"box {box} is too small to crop at {size_px} px")
    shape = (max(1, round((x1 - x0) * crop_per_m)), max(1, round((y1 - y0) * crop_per_m)))
    d = datum or {}
    T_structure_world = se2_matrix(
        float(d.get("x", 0.0)), float(d.get("y", 0.0)), float(d.get("yaw", 0.0))
    )
    T_structure_crop = np.array([[1 / crop_per_m, 0, x0], [0, 1 / crop_per_m, y0], [0, 0, 1]])
    T_mosaic_world = np.array(
        [
            [px_per_m, 0, -origin_m[0] * px_per_m],
            [0, px_per_m, -origin_m[1] * px_per_m],
            [0, 0, 1],
        ]
    )
    T_mosaic_crop = T_mosaic_world @ np.linalg.inv(T_structure_world) @ T_structure_crop
    return T_mosaic_crop[:2], shape


def _bounds(
    A: NDArray[np.float64], shape: tuple[int, int], limit: tuple[int, int]
) -> tuple[int, int, int, int] | None:
    """The mosaic pixels (x, y, w, h) under a crop of ``shape`` mapped by ``A``, within a
    mosaic of ``limit`` (width, height) px; None when none are."""
    w, h = shape
    corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float) @ A.T
    x0 = max(0, int(np.floor(corners[:, 0].min())) - 2)
    y0 = max(0, int(np.floor(corners[:, 1].min())) - 2)
    x1 = min(limit[0], int(np.ceil(corners[:, 0].max())) + 2)
    y1 = min(limit[1], int(np.ceil(corners[:, 1].max())) + 2)
    return None if x1 <= x0 or y1 <= y0 else (x0, y0, x1 - x0, y1 - y0)


def crop_mosaic(
    results: Path, stitch: dict[str, Any], datum: dict[str, Any] | None, box: Box, size_px: int
) -> NDArray[np.uint8]:
    """A session's mosaic over ``box`` (structure frame, m), ``size_px`` along the box's
    longer side: (H, W, 4) BGRA, transparent where the mosaic does not reach. From the
    full-resolution mosaic (its Deep Zoom tiles) where the crop needs its detail, else
    from the overview. ``results``: the session's results folder; ``stitch``: its stitch
    job's result (``origin_m``, ``px_per_m``, ``overview_scale``, ``overview_path``)."""
    origin = (float(stitch["origin_m"][0]), float(stitch["origin_m"][1]))
    full_ppm = float(stitch["px_per_m"])
    small_ppm = full_ppm * float(stitch.get("overview_scale", 1.0))
    crop_per_m = size_px / max(box[2] - box[0], box[3] - box[1])
    A, shape = crop_affine(box, size_px, datum, origin, full_ppm)
    image: np.ndarray | None = None
    offset, source_ppm = (0, 0), full_ppm
    world = results / "mosaic.json"
    if crop_per_m > small_ppm * 1.01 and world.is_file():
        doc = json.loads(world.read_text())
        region = _bounds(A, shape, (int(doc["width_px"]), int(doc["height_px"])))
        if region is None:
            return np.zeros((shape[1], shape[0], 4), np.uint8)
        if region[2] * region[3] <= MAX_SOURCE_PX:
            image = read_region(results, *region)
            offset = region[:2]
    if image is None:
        A, shape = crop_affine(box, size_px, datum, origin, small_ppm)
        source_ppm = small_ppm
        overview = cv2.imread(
            str(results / Path(str(stitch["overview_path"])).name), cv2.IMREAD_COLOR
        )
        if overview is None:
            raise FileNotFoundError(f"no mosaic overview in {results}")
        region = _bounds(A, shape, (overview.shape[1], overview.shape[0]))
        if region is None:
            return np.zeros((shape[1], shape[0], 4), np.uint8)
        x, y, w, h = region
        image, offset = overview[y : y + h, x : x + w], (x, y)
    if image is None:
        raise FileNotFoundError(f"no mosaic in {results}")
    A = A.copy()
    A[:, 2] -= offset
    shrink = crop_per_m / source_ppm
    if shrink < 0.5:  # area-averaged first: a warp samples, and would alias
        h, w = image.shape[:2]
        size = (max(1, round(w * shrink)), max(1, round(h * shrink)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        A = A * np.array([[size[0] / w], [size[1] / h]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    bgr = cv2.warpAffine(image, A, shape, flags=flags, borderMode=cv2.BORDER_CONSTANT)
    inside = np.full(image.shape[:2], 255, np.uint8)
    alpha = cv2.warpAffine(inside, A, shape, flags=flags, borderMode=cv2.BORDER_CONSTANT)
    return cast(NDArray[np.uint8], np.dstack([bgr, alpha]))


def encode_png(image: NDArray[np.uint8]) -> bytes:
    """PNG bytes of a BGR or BGRA image."""
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("could not encode the crop")
    return buf.tobytes()
