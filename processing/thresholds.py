"""Thresholds and component selection shared by the detectors: Sauvola's local threshold,
hysteresis and seeded region growing, components kept by flag or by size."""

from __future__ import annotations

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from processing.labels import component_flags, lookup


def select_components(
    labels: NDArray[np.int32], stats: NDArray[np.int32], keep: NDArray[np.bool_]
) -> NDArray[np.bool_]:
    """Mask of the components whose ``keep`` flag is set (``labels`` and ``stats`` from
    ``cv2.connectedComponentsWithStats``, label 0 never kept).

    A lookup ``keep[labels]`` costs ~3 ns per pixel of the whole image; when the kept (or
    the dropped) components are few, painting them inside their boxes costs far less.
    """
    keep = keep.copy()
    keep[0] = False
    areas = stats[:, cv2.CC_STAT_WIDTH].astype(np.int64) * stats[:, cv2.CC_STAT_HEIGHT]
    kept, dropped = np.flatnonzero(keep), np.flatnonzero(~keep[1:]) + 1
    lookup_cost = 3.0 * labels.size
    paint_kept = 1.5 * areas[kept].sum() + 3000.0 * len(kept)
    paint_dropped = 1.5 * areas[dropped].sum() + 3000.0 * len(dropped) + 0.5 * labels.size
    if min(paint_kept, paint_dropped) >= lookup_cost:
        return lookup(labels, keep)
    if paint_kept <= paint_dropped:
        out = np.zeros(labels.shape, bool)
        ids, value = kept, True
    else:
        out = labels > 0
        ids, value = dropped, False
    for i in ids.tolist():
        x, y, w, h = (int(v) for v in stats[i, :4])
        box = out[y : y + h, x : x + w]
        box[labels[y : y + h, x : x + w] == i] = value
    return out


def seeded_regions(
    candidates: NDArray[np.bool_],
    seeds: NDArray[np.bool_],
    *,
    min_area_px: int = 0,
    max_half_width_px: float | None = None,
) -> NDArray[np.bool_]:
    """Region growing from seeds: the 8-connected regions of ``candidates`` that hold a
    seed pixel (and at least ``min_area_px`` pixels, and no inscribed radius over
    ``max_half_width_px`` when given: wider than a crack)."""
    grown = (candidates | seeds).astype(np.uint8)
    n, labels = cv2.connectedComponents(grown, connectivity=8)
    dist = None
    if max_half_width_px is not None:
        # components are separated by background, so each one's distance to the
        # background is its own: one transform serves all
        dist = cv2.distanceTransform(np.pad(grown, 1), cv2.DIST_L2, 3)[1:-1, 1:-1]
    area, seeded, thick = component_flags(labels, n, seeds, dist, max_half_width_px or np.inf)
    keep = seeded & (area >= min_area_px) & ~thick
    keep[0] = False
    return lookup(labels, keep)


def hysteresis(
    response: NDArray[np.floating], low: float, high: float, *, min_area_px: int = 0
) -> NDArray[np.bool_]:
    """Hysteresis thresholding: regions above ``low`` that hold a pixel above ``high``."""
    return seeded_regions(response > low, response > high, min_area_px=min_area_px)


def sauvola_threshold(
    gray: NDArray[np.uint8], window: int, k: float, r: float = 127.5
) -> NDArray[np.float32]:
    """Sauvola's local threshold m·(1 + k·(s/r − 1)) from box-filtered moments (as scikit-image)."""
    mean, sq = _local_moments(gray, window)
    var = cv2.max(cv2.subtract(sq, cv2.multiply(mean, mean)), 0.0)
    factor = cv2.sqrt(var)
    cv2.addWeighted(factor, k / r, factor, 0.0, 1.0 - k, dst=factor)  # 1 + k (s/r - 1)
    return cv2.multiply(mean, factor)


def below_sauvola(
    gray: NDArray[np.uint8], window: int, k: float, r: float = 127.5
) -> NDArray[np.bool_]:
    """``gray < sauvola_threshold(gray, window, k, r)`` in one compiled pass after the box filters."""
    mean, sq = _local_moments(gray, window)
    out = np.empty(gray.shape, np.bool_)
    _below_sauvola(gray, mean, sq, np.float32(k), np.float32(r), out)
    return out


def _local_moments(
    gray: NDArray[np.uint8], window: int
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Mean and mean square over a ``window``-wide square (reflected borders)."""
    size = (window | 1, window | 1)
    mean = cv2.boxFilter(gray, cv2.CV_32F, size, borderType=cv2.BORDER_REFLECT)
    sq = cv2.sqrBoxFilter(gray, cv2.CV_32F, size, borderType=cv2.BORDER_REFLECT)
    return mean, sq


@numba.njit(nogil=True, cache=True)
def _below_sauvola(
    gray: NDArray[np.uint8],
    mean: NDArray[np.float32],
    sq: NDArray[np.float32],
    k: np.float32,
    r: np.float32,
    out: NDArray[np.bool_],
) -> None:  # pragma: no cover - compiled
    rows, cols = gray.shape
    for y in range(rows):
        for x in range(cols):
            m = mean[y, x]
            var = max(sq[y, x] - m * m, np.float32(0))
            out[y, x] = gray[y, x] < m * (1 + k * (np.sqrt(var) / r - 1))


def remove_small(mask: NDArray[np.bool_], min_area_px: int) -> NDArray[np.bool_]:
    """Drop connected components smaller than ``min_area_px`` pixels."""
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    area, _, _ = component_flags(labels, n)
    keep = area >= min_area_px
    keep[0] = False
    return lookup(labels, keep)
