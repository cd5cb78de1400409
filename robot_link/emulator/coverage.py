"""How much of the emulated plate a run's camera footprint covered, judged from the
emulator's header and true states alone (as an acceptance check judges a sweep)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray


def footprint_coverage(
    header: dict[str, Any], states: Iterable[dict[str, Any]], cell_m: float = 0.002
) -> tuple[float, NDArray[np.bool_]]:
    """Fraction of the plate inside the camera footprint of at least one state, and the
    (H, W) grid of covered cells (``cell_m`` square, row 0 at y = 0)."""
    w, h = header["plate"]["width"], header["plate"]["height"]
    across = header["camera_footprint"]["width"]
    along = header["camera_footprint"]["height"]
    grid = np.zeros((int(np.ceil(h / cell_m)), int(np.ceil(w / cell_m))), np.uint8)
    corners = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [along / 2, across / 2]
    for s in states:
        c, si = np.cos(s["heading"]), np.sin(s["heading"])
        pts = corners @ np.array([[c, si], [-si, c]]) + [s["x"], s["y"]]
        cv2.fillConvexPoly(grid, np.round(pts / cell_m * 16).astype(np.int32), 1, cv2.LINE_8, 4)
    covered = grid.astype(bool)
    return float(covered.mean()), covered
