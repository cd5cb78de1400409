"""Whether a crack one visit's detector found and the other's missed is still there: the
other image, carried into the first's frame, is as dark along the crack's line (against
the line's surroundings) as the image that shows it. Detectors flicker with lighting and
resampling; the grey levels along a line do not."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray


def gray_float(image: NDArray[np.uint8]) -> NDArray[np.float32]:
    """(H, W) float32 grey levels of a grey or BGR image."""
    g = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return np.asarray(g, np.float32)


def line_contrast(gray: NDArray[np.float32], line: NDArray[np.bool_], ring_px: int = 6) -> float:
    """How much darker the pixels along ``line`` (a skeleton, (H, W)) are than a ring
    4 to ``ring_px`` px around it (median grey levels)."""
    u8 = line.astype(np.uint8)
    core = cv2.dilate(u8, np.ones((3, 3), np.uint8)).astype(bool)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ring_px + 1, 2 * ring_px + 1))
    ring = cv2.dilate(u8, k).astype(bool) & ~cv2.dilate(u8, np.ones((7, 7), np.uint8)).astype(bool)
    if not core.any() or not ring.any():
        return 0.0
    return float(np.median(gray[ring]) - np.median(gray[core]))


def still_there(
    line: NDArray[np.bool_],
    seen_in: NDArray[np.float32],
    other_here: NDArray[np.float32],
    keep: float = 0.5,
) -> bool:
    """Whether the other image (``other_here``, in the same frame as ``seen_in``) is at
    least ``keep`` times as dark along ``line`` as the image it was detected in."""
    seen = line_contrast(seen_in, line)
    return seen > 0 and line_contrast(other_here, line) >= keep * seen
