"""The downward camera's motion in the live map, as in the ``map`` job
(:mod:`server.jobs.map_camera`): in the live map's worker each stored frame is registered
to the one before it (from the odometry's motion, as the job does without a mosaic), and
once frames on both sides of a cloud step have arrived, the chain's steps become a camera
edge between the two clouds in the live pose graph (:func:`camera_edge`), beside the ToF's
registrations and the odometry."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from processing.mapping.camera_motion import CameraModel, FootStep
from processing.mapping.planar_camera import camera_height, downward_camera, planar_factors
from processing.poses import relative_se2
from processing.stitching.mosaic import camera_poses

WAITING = 50  # cloud steps waiting for their frames, at most (a session without frames)


@dataclass
class FrameChain:
    """One live session's frames, registered pair by pair as they arrive (grey images: only
    the last is kept), and the cloud steps still waiting for frames past their end."""

    calibration: dict[str, Any]  # the session's camera calibration
    T_robot_tof: NDArray[np.float64]
    times: list[float] = field(default_factory=list)
    deltas: list[NDArray[np.float64] | None] = field(default_factory=list)
    waiting: list[tuple[int, float, float]] = field(default_factory=list)  # (cloud, t0, t1)
    _last: tuple[NDArray[np.uint8], NDArray[np.float64]] | None = None  # image, camera px pose
    _model: tuple[CameraModel, float] | None = None

    def add(self, image: NDArray[np.uint8], t: float, robot_pose: NDArray[np.float64]) -> None:
        """Frame ``image`` (H, W grey) taken at ``t`` where the odometry put the robot
        (x, y, yaw), registered to the frame before it."""
        from processing.mapping.frame_pairs import frame_deltas

        if self.times and t <= self.times[-1]:
            return  # out of order: the chain keeps time
        px_per_m = float(self.calibration["px_per_m"])
        mount = self.calibration.get("T_robot_camera", [0.0, 0.0, 0.0])
        pose = camera_poses(np.asarray(robot_pose, np.float64)[None], mount, px_per_m)[0]
        if self._model is None:
            h, w = image.shape
            height_m = camera_height(w, px_per_m, self.calibration.get("height_m"))
            model = downward_camera(w, h, px_per_m, mount, self.T_robot_tof, height_m)
            self._model = model, height_m
        if self._last is not None:
            last, last_pose = self._last
            delta = None
            if last.shape == image.shape:
                delta = frame_deltas([last, image], [relative_se2(last_pose, pose)])[0]
            self.deltas.append(delta)
        self.times.append(t)
        self._last = image, pose

    def step(self, t0: float, t1: float) -> FootStep | None:
        """The footprint step from ``t0`` to ``t1`` (None where the frames do not link them
        or have not reached ``t1`` yet)."""
        if self._model is None or not self.times or t0 < self.times[0] or t1 > self.times[-1]:
            return None
        times = np.asarray(self.times)
        first = int(np.searchsorted(times, t0, side="right")) - 1
        last = int(np.searchsorted(times, t1, side="left"))
        model, height_m = self._model
        factors = planar_factors(
            self.deltas[first:last], times[first : last + 1], np.array([t0, t1]), model, height_m
        )
        return factors.steps[0]

    def edges(
        self, poses: NDArray[np.float64]
    ) -> list[tuple[int, int, NDArray[np.float64], NDArray[np.float64]]]:
        """(source, target, T_target_source, information) of each waiting cloud step whose
        frames have now arrived, from the current ``poses`` (N, 4, 4); those still waiting
        (frames yet to come, or none that cover them) stay or are dropped."""
        from processing.mapping.camera_motion import camera_edge

        out, still = [], []
        for i, t0, t1 in self.waiting:
            if not self.times or t1 > self.times[-1]:
                still.append((i, t0, t1))
                continue
            step = self.step(t0, t1)
            if step is None or self._model is None or i >= len(poses):
                continue
            model, height_m = self._model
            X, info = camera_edge(step, np.linalg.inv(poses[i - 1]) @ poses[i], height_m, model)
            out.append((i, i - 1, X, info))
        self.waiting = still[-WAITING:]
        return out
