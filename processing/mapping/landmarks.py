"""Plane landmarks of the pose graph: the large planes each cloud sees (deck plate, web,
stiffener faces) matched to planes seen before, each landmark a frame on its plane (z
along the normal) whose sightings become graph edges (:func:`processing.mapping.planes.plane_edge`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from processing.mapping.params import PlaneParams
from processing.mapping.planes import Plane, plane_edge, plane_frame, same_plane, to_frame

reg = o3d.pipelines.registration


class PlaneLandmarks:
    """The planes of every cloud so far and the landmarks they were matched to."""

    def __init__(self, params: PlaneParams) -> None:
        self.params = params
        self.planes: list[list[Plane]] = []  # large planes of each cloud (sensor frame)
        self.sightings: list[list[tuple[int, int]]] = []  # per landmark: (cloud, plane index)
        self.poses: list[NDArray[np.float64]] = []  # T_world_landmark

    def __len__(self) -> int:
        return len(self.sightings)

    @property
    def tying(self) -> int:
        """Landmarks seen often enough to tie the clouds that see them."""
        return sum(len(s) >= self.params.min_sightings for s in self.sightings)

    def plane(self, m: int) -> Plane:
        """Landmark m as a plane in the world (its frame's z axis and origin)."""
        T = self.poses[m]
        return Plane(T[:3, 2].copy(), float(-T[:3, 2] @ T[:3, 3]), T[None, :3, 3].copy())

    def _same(self, a: Plane, b: Plane) -> bool:
        return same_plane(a, b, self.params.max_angle_deg, self.params.max_offset_m)

    def associate(self, i: int, pose: NDArray[np.float64]) -> None:
        """Match cloud i's planes (its pose ``pose``, current estimate) to the landmarks; an
        unmatched one becomes a landmark."""
        for k, plane in enumerate(self.planes[i]):
            world = to_frame(plane, pose)
            m = next((m for m in range(len(self)) if self._same(world, self.plane(m))), None)
            if m is None:
                self.sightings.append([(i, k)])
                self.poses.append(plane_frame(world))
            else:
                self.sightings[m].append((i, k))

    def merge(self) -> None:
        """Merge landmarks that the optimised poses show to be one plane (seen apart before)."""
        m = 0
        while m < len(self):
            other = next(
                (o for o in range(m + 1, len(self)) if self._same(self.plane(m), self.plane(o))),
                None,
            )
            if other is None:
                m += 1
                continue
            self.sightings[m] += self.sightings.pop(other)
            self.poses.pop(other)

    def edges(
        self, first_node: int, pose_of: Callable[[int], NDArray[np.float64]]
    ) -> tuple[list[int], list[reg.PoseGraphEdge]]:
        """The landmarks seen often enough to tie clouds (their nodes numbered from
        ``first_node`` in that order) and the edges from each sighting to its landmark's
        node: :func:`plane_edge` against the plane z = 0 of the landmark's frame, uncertain
        (the robust optimisation can drop a sighting that disagrees), and a weak prior tying
        each landmark to its first sighting along what planes leave free. ``pose_of(i)``
        is cloud i's current pose."""
        active = [m for m, s in enumerate(self.sightings) if len(s) >= self.params.min_sightings]
        edges = []
        on_plane = Plane(np.array([0.0, 0.0, 1.0]), 0.0, np.zeros((1, 3)))
        for node, m in enumerate(active, start=first_node):
            T_L = np.linalg.inv(self.poses[m])
            for i, k in self.sightings[m]:
                measurement, info = plane_edge(
                    self.planes[i][k], on_plane, T_L @ pose_of(i), self.params.sigma_m
                )
                edges.append(reg.PoseGraphEdge(i, node, measurement, info, uncertain=True))
            anchor = self.sightings[m][0][0]
            edges.append(
                reg.PoseGraphEdge(anchor, node, T_L @ pose_of(anchor), np.eye(6), uncertain=False)
            )
        return active, edges
