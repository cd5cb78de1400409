"""Per-component sums and selection over a label image, in one compiled pass each.

OpenCV labels components fast, but its statistics pass and NumPy's ``keep[labels]``
lookup cost several nanoseconds per pixel; these loops cost about one, and release the
GIL so image tiles are processed on both cores.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


@numba.njit(nogil=True, cache=True)
def _flags(
    labels: NDArray[np.int32],
    n: int,
    seeds: NDArray[np.bool_],
    dist: NDArray[np.float32],
    max_dist: float,
) -> tuple[NDArray[np.int64], NDArray[np.bool_], NDArray[np.bool_]]:  # pragma: no cover - compiled
    area = np.zeros(n, np.int64)
    seeded = np.zeros(n, np.bool_)
    thick = np.zeros(n, np.bool_)
    rows, cols = labels.shape
    for y in range(rows):
        for x in range(cols):
            a = labels[y, x]
            if a:
                area[a] += 1
                if seeds[y, x]:
                    seeded[a] = True
                if dist[y, x] > max_dist:
                    thick[a] = True
    return area, seeded, thick


def component_flags(
    labels: NDArray[np.int32],
    n: int,
    seeds: NDArray[np.bool_] | None = None,
    dist: NDArray[np.float32] | None = None,
    max_dist: float = np.inf,
) -> tuple[NDArray[np.int64], NDArray[np.bool_], NDArray[np.bool_]]:
    """Per label 0..n-1: pixel count, whether it holds a ``seeds`` pixel, and whether it
    holds a pixel with ``dist`` over ``max_dist``."""
    seeds = np.zeros((1, 1), np.bool_) if seeds is None else seeds
    dist = np.zeros((1, 1), np.float32) if dist is None else dist
    if seeds.shape != labels.shape:
        seeds = np.broadcast_to(np.zeros((1, 1), np.bool_), labels.shape)
    if dist.shape != labels.shape:
        dist, max_dist = np.broadcast_to(np.zeros((1, 1), np.float32), labels.shape), np.inf
    return _flags(labels, n, seeds, dist, float(max_dist))


@numba.njit(nogil=True, cache=True)
def _lookup(
    labels: NDArray[np.int32], keep: NDArray[np.bool_], out: NDArray[np.bool_]
) -> None:  # pragma: no cover - compiled
    rows, cols = labels.shape
    for y in range(rows):
        for x in range(cols):
            out[y, x] = keep[labels[y, x]]


def lookup(labels: NDArray[np.int32], keep: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``keep[labels]``: the mask of the components whose flag is set."""
    out = np.empty(labels.shape, np.bool_)
    _lookup(labels, keep, out)
    return out


@numba.njit(nogil=True, cache=True)
def _stats(
    labels: NDArray[np.int32], n: int, stats: NDArray[np.int32], sums: NDArray[np.float64]
) -> None:  # pragma: no cover - compiled
    rows, cols = labels.shape
    for i in range(n):
        stats[i, 0], stats[i, 1], stats[i, 2], stats[i, 3] = cols, rows, -1, -1
    for y in range(rows):
        for x in range(cols):
            a = labels[y, x]
            stats[a, 4] += 1
            if a:
                if x < stats[a, 0]:
                    stats[a, 0] = x
                if x > stats[a, 2]:
                    stats[a, 2] = x
                if y < stats[a, 1]:
                    stats[a, 1] = y
                if y > stats[a, 3]:
                    stats[a, 3] = y
                sums[a, 0] += x
                sums[a, 1] += y


def component_stats(
    labels: NDArray[np.int32], n: int
) -> tuple[NDArray[np.int32], NDArray[np.float64]]:
    """``cv2.connectedComponentsWithStats``'s statistics (x, y, width, height, area) and
    centroids from a label image, in one compiled pass (OpenCV's own costs twice its
    labelling); the background's row holds the image box and its area, centroid 0."""
    stats = np.zeros((n, 5), np.int32)
    sums = np.zeros((n, 2))
    _stats(labels, n, stats, sums)
    rows, cols = labels.shape
    stats[:, 2] -= stats[:, 0] - 1  # x1 → width
    stats[:, 3] -= stats[:, 1] - 1
    stats[0, :4] = (0, 0, cols, rows)
    area = np.maximum(stats[:, 4], 1)[:, None]
    centroids = sums / area
    centroids[0] = 0.0
    return stats, centroids
