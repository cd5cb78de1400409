"""The map tracking registers to: points and normals of every cloud so far, summed per
voxel in the world frame and grown one cloud at a time (each point lands in one voxel,
so adding a cloud costs its own size, not the map's)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

_OFFSET = 1 << 20  # voxel indices are shifted positive and packed 21 bits per axis


def voxel_keys(points: NDArray[np.float64], voxel_m: float) -> NDArray[np.int64]:
    """One int64 key per point (K, 3) for the voxel of ``voxel_m`` holding it: (K,)."""
    k = np.floor(points / voxel_m).astype(np.int64) + _OFFSET
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


def _sum_per_key(
    keys: NDArray[np.int64], values: NDArray[np.float64]
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.intp]]:
    """Sorted unique keys (U,), the rows of ``values`` (K, C) summed per key (U, C), counts (U,)."""
    unique, inverse, count = np.unique(keys, return_inverse=True, return_counts=True)
    sums: NDArray[np.float64] = np.column_stack(
        [np.bincount(inverse, weights=values[:, c], minlength=len(unique)) for c in range(6)]
    )
    return unique, sums, count


def voxel_mean(
    points: NDArray[np.float64], normals: NDArray[np.float64], voxel_m: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Points (K, 3) and normals (K, 3) averaged per voxel of ``voxel_m``: (M, 3) means and
    (M, 3) unit normals (the map, where many clouds' points of one surface fall together)."""
    _, sums, count = _sum_per_key(voxel_keys(points, voxel_m), np.hstack([points, normals]))
    return sums[:, :3] / count[:, None], _unit(sums[:, 3:])


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


class VoxelMap:
    """Sums of points and normals per voxel of ``voxel_m`` (world frame), kept sorted by
    voxel key; :meth:`add` merges a cloud, :meth:`crop` reads the means in a box."""

    def __init__(self, voxel_m: float) -> None:
        self.voxel_m = voxel_m
        self._keys = np.zeros(0, np.int64)
        self._sums = np.zeros((0, 6))
        self._counts = np.zeros(0, np.int64)
        self._means = np.zeros((0, 3))

    def __len__(self) -> int:
        return len(self._keys)

    def add(self, points: NDArray[np.float64], normals: NDArray[np.float64]) -> None:
        """Merge points (K, 3) and their normals (K, 3), world frame."""
        if len(points) == 0:
            return
        keys, sums, counts = _sum_per_key(
            voxel_keys(points, self.voxel_m), np.hstack([points, normals])
        )
        at = np.searchsorted(self._keys, keys)
        seen = at < len(self._keys)
        seen[seen] = self._keys[at[seen]] == keys[seen]
        self._sums[at[seen]] += sums[seen]
        self._counts[at[seen]] += counts[seen]
        new = ~seen
        self._keys = np.insert(self._keys, at[new], keys[new])
        self._sums = np.insert(self._sums, at[new], sums[new], axis=0)
        self._counts = np.insert(self._counts, at[new], counts[new])
        self._means = self._sums[:, :3] / self._counts[:, None]

    def crop(
        self, lo: NDArray[np.float64], hi: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Means (M, 3) and unit normals (M, 3) of the voxels whose mean lies in [lo, hi]."""
        inside = np.all((self._means >= lo) & (self._means <= hi), axis=1)
        return self._means[inside], _unit(self._sums[inside, 3:])
