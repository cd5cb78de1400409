"""Which order an odometry file's quaternions were written in, told by the clouds.

TUM files hold ``qx qy qz qw``; a file written ``qw qx qy qz`` parses as well and yields
rotations that are wrong by a large, pose-dependent turn. The clouds tell the two apart:
placed by the right rotations, views of the same surface land on each other, so the
clouds together fill few voxels; placed by the wrong ones, each cloud is turned about its
own origin by a different error and the same surface is smeared over many voxels. On every
simulated structure the wrong order fills 2-4x the voxels of the right one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class OrderParams:
    """How the two readings are compared."""

    # a few odometry errors (2 cm a step) wide: a right reading's overlapping views share voxels
    voxel_m: float = 0.05
    points_per_cloud: int = 2000  # a sample of each cloud is enough to count voxels
    # the other reading is taken when the given one fills this many times its voxels
    decisive_ratio: float = 1.5


@dataclass(frozen=True)
class OrderCheck:
    """The voxels the clouds fill placed by each reading, and whether to swap."""

    given_voxels: int
    other_voxels: int
    swap: bool

    @property
    def ratio(self) -> float:
        """Voxels of the given reading over the other's (> 1: the other fits better)."""
        return self.given_voxels / max(1, self.other_voxels)


def occupied_voxels(
    clouds: Sequence[NDArray[np.floating]],
    poses: NDArray[np.floating],
    params: OrderParams = OrderParams(),
) -> int:
    """Voxels of ``params.voxel_m`` filled by ``clouds`` ((K, 3) each, sensor frame, NaN
    rows ignored) placed by ``poses`` ((N, 4, 4) T_world_sensor)."""
    keys = []
    for cloud, T in zip(clouds, poses):
        pts = np.asarray(cloud, np.float64).reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(axis=1)]
        pts = pts[:: max(1, len(pts) // params.points_per_cloud)]
        world = pts @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3]
        keys.append(np.floor(world / params.voxel_m).astype(np.int64))
    if not keys:
        return 0
    return len(np.unique(np.concatenate(keys), axis=0))


def check_order(
    clouds: Sequence[NDArray[np.floating]],
    given: NDArray[np.floating],
    other: NDArray[np.floating],
    params: OrderParams = OrderParams(),
) -> OrderCheck:
    """Whether the ``other`` reading of the odometry ((N, 4, 4)) places ``clouds`` so much
    more consistently than the ``given`` one that it must be the file's order."""
    a = occupied_voxels(clouds, given, params)
    b = occupied_voxels(clouds, other, params)
    return OrderCheck(a, b, swap=a > params.decisive_ratio * max(1, b))
