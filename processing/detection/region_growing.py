"""Region growing from the boundaries of detected regions (paper §3.3.3, eq. (15))."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray


def grow_regions(
    image: NDArray[np.generic], seeds: NDArray[np.bool_], max_diff: float, *, max_iter: int = 100
) -> NDArray[np.bool_]:
    """Grow each connected region of ``seeds`` over 8-neighbours similar to it.

    A neighbour N joins the region S it touches when e = |g_S - g_N| < ``max_diff``
    (eq. (15)), g_S being the region's current mean intensity; regions' boundary pixels
    are the seeds, and growth stops when no pixel joins or after ``max_iter`` rounds.

    Parameters
    ----------
    image : (M, N) grey image.
    seeds : (M, N) bool mask of the initially detected regions.
    max_diff : the similarity threshold (grey levels).

    Returns
    -------
    (M, N) bool mask, a superset of ``seeds``.
    """
    if image.shape != seeds.shape:
        raise ValueError(f"image {image.shape} and seeds {seeds.shape} differ in shape")
    if max_diff <= 0 or not seeds.any():
        return seeds.astype(bool).copy()
    img = image.astype(np.float32)
    n, labels = cv2.connectedComponents(seeds.astype(np.uint8), connectivity=8)
    labels = labels.astype(np.float32)  # exact for < 2**24 regions; cv2.dilate takes float32
    flat = labels.ravel().astype(np.int64)
    sums = np.bincount(flat, weights=img.ravel(), minlength=n)
    counts = np.bincount(flat, minlength=n).astype(np.float64)
    kernel = np.ones((3, 3), np.uint8)
    for _ in range(max_iter):
        near = cv2.dilate(labels, kernel)
        frontier = (labels == 0) & (near > 0)
        if not frontier.any():
            break
        idx = near[frontier].astype(np.int64)
        means = sums / np.maximum(counts, 1)
        ok = np.abs(img[frontier] - means[idx]) < max_diff
        if not ok.any():
            break
        ys, xs = np.nonzero(frontier)
        ys, xs, idx = ys[ok], xs[ok], idx[ok]
        labels[ys, xs] = idx
        np.add.at(sums, idx, img[ys, xs])
        np.add.at(counts, idx, 1)
    return labels > 0
