"""Where a mosaic shows the steel surface, and how bright that surface typically is."""

from __future__ import annotations

from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray


def _quarter(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """An image at a quarter of its resolution (area average)."""
    for _ in range(2):  # two halvings: OpenCV's 2x area path is ~15x faster than one 4x
        h, w = image.shape[:2]
        image = cast(
            NDArray[np.uint8],
            cv2.resize(image, (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_AREA),
        )
    return image


def _covered_quarter(coverage: NDArray[np.generic]) -> NDArray[np.bool_]:
    """4x4 blocks fully inside the covered area (``coverage`` > 0)."""
    covered = cv2.threshold(coverage.astype(np.uint8, copy=False), 0, 255, cv2.THRESH_BINARY)[1]
    return _quarter(cast(NDArray[np.uint8], covered)) == 255


def _surface_background_quarter(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """The grey surface brightness with dark details closed away (a 45-px disk), at a
    quarter of the resolution: it varies slowly."""
    small = _quarter(
        cast(NDArray[np.uint8], cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
        if image.ndim == 3
        else image
    )
    return cast(
        NDArray[np.uint8],
        cv2.morphologyEx(
            small, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (11, 11))
        ),
    )


def surface_level(image: NDArray[np.uint8], coverage: NDArray[np.generic]) -> float:
    """The surface's typical brightness: median of the grey background over covered pixels."""
    covered = _covered_quarter(coverage)
    return float(np.median(_surface_background_quarter(image)[covered])) if covered.any() else 0.0


def on_surface(
    image: NDArray[np.uint8], coverage: NDArray[np.generic], level: float | None = None
) -> NDArray[np.bool_]:
    """Where a mosaic shows the steel surface: not far darker than the surface typically
    is (``level``; beyond a plate's edge the camera sees the dark void below), and well
    inside the covered area (its edge is a dark step, not a crack); decided on 4x4 blocks."""
    background = _surface_background_quarter(image)
    covered = _covered_quarter(coverage)
    if level is None:
        level = float(np.median(background[covered])) if covered.any() else 0.0
    surface = ((background > 0.4 * level) & covered).astype(np.uint8)
    # ~15 px on each side
    surface = cast(NDArray[np.uint8], cv2.erode(surface, np.ones((7, 7), np.uint8)))
    h, w = image.shape[:2]
    full = np.zeros((h, w), np.uint8)
    up = cv2.resize(
        surface, (surface.shape[1] * 4, surface.shape[0] * 4), interpolation=cv2.INTER_NEAREST
    )
    full[: up.shape[0], : up.shape[1]] = up[:h, :w]
    return full > 0
