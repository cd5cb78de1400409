"""Corrosion (rust) detection by colour: rust's hues at a saturation the image itself
separates from grey paint."""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.detection.thresholds import remove_small


@dataclass(frozen=True)
class CorrosionParams:
    """Options of the rust detector: rust's hues (OpenCV's 0–180 scale, red wrapping round
    through 180) and the least saturation; above that, the image's own split between
    saturated and grey pixels (Otsu on saturation) decides, so that on a colourful surface
    only the clearly rust-coloured part counts."""

    hue_max: int = 30
    hue_wrap_from: int = 170
    min_saturation: int = 40
    min_area_px: int = 400


def rust_saturation(image: NDArray[np.uint8], params: CorrosionParams = CorrosionParams()) -> float:
    """The saturation above which a rust-hued pixel of a BGR image is rust: Otsu's split of
    the image's saturation (on at most ~1 MP of it), at least ``params.min_saturation``."""
    h, w = image.shape[:2]
    step = max(1, int(np.sqrt(h * w / 1e6)))
    hsv = cv2.cvtColor(image[::step, ::step], cv2.COLOR_BGR2HSV)
    t, _ = cv2.threshold(hsv[..., 1], 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return float(max(t, params.min_saturation))


def corrosion_candidates(
    image: NDArray[np.uint8],
    params: CorrosionParams = CorrosionParams(),
    saturation: float | None = None,
) -> NDArray[np.bool_]:
    """Rust-coloured pixels of a BGR image (rust hue, saturation above ``saturation``, by
    default :func:`rust_saturation` of the image), cleaned by an opening and a closing;
    components of any size."""
    sat = rust_saturation(image, params) if saturation is None else saturation
    hsv = cv2.cvtColor(cv2.GaussianBlur(image, (5, 5), 0), cv2.COLOR_BGR2HSV)
    low = int(np.floor(sat)) + 1
    mask = cast(NDArray[np.uint8], cv2.inRange(hsv, (0, low, 0), (params.hue_max, 255, 255)))
    mask |= cast(
        NDArray[np.uint8], cv2.inRange(hsv, (params.hue_wrap_from, low, 0), (180, 255, 255))
    )
    mask = cast(
        NDArray[np.uint8], cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    )
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8)) > 0


def detect_corrosion(
    image: NDArray[np.generic], *, params: CorrosionParams = CorrosionParams()
) -> NDArray[np.bool_]:
    """Boolean (H, W) mask of rust-coloured areas (needs a BGR image; gray gives none)."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        return np.zeros(image.shape[:2], bool)
    bgr = cast(NDArray[np.uint8], image)  # its dtype checked above
    return remove_small(corrosion_candidates(bgr, params), params.min_area_px)
