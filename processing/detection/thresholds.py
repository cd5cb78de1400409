"""Component selection shared by the detectors: components kept by flag or by size."""

from __future__ import annotations

from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.detection.labels import component_flags, lookup


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


def remove_small(mask: NDArray[np.bool_], min_area_px: int) -> NDArray[np.bool_]:
    """Drop connected components smaller than ``min_area_px`` pixels."""
    n, found = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    labels = cast(NDArray[np.int32], found)
    area, _, _ = component_flags(labels, n)
    keep = area >= min_area_px
    keep[0] = False
    return lookup(labels, keep)
