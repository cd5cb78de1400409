"""The downward camera's motion in the live map, as in the ``map`` job
(:mod:`server.jobs.map_camera`): in the live map's worker each stored frame is registered
to the one before it (from the odometry's motion, as the job does without a mosaic), and
once frames on both sides of a cloud step have arrived, the chain's steps become a camera
edge between the two clouds in the live pose graph (:func:`camera_edge`), beside the ToF's
registrations and the odometry. Each frame is also registered to the earlier frame, before
the chain's last break, that the odometry says overlaps it most (the lane before, passed
again after a turn its frames did not follow): that match, carried along the chain to the
clouds nearest both frames, is a loop edge (robust, as the ToF's loop closures are), which
holds a lane's heading where the turn onto it left the camera nothing to register."""

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
KEPT = 2000  # frames kept for registering lanes passed again (as they came: ~50 kB each)


@dataclass
class FrameChain:
    """One live session's frames, registered pair by pair as they arrive (the last as a grey
    image, the earlier ones as they came), the matches of lanes passed again, and the cloud
    steps still waiting for frames past their end."""

    calibration: dict[str, Any]  # the session's camera calibration
    T_robot_tof: NDArray[np.float64]
    times: list[float] = field(default_factory=list)
    deltas: list[NDArray[np.float64] | None] = field(default_factory=list)
    waiting: list[tuple[int, float, float]] = field(default_factory=list)  # (cloud, t0, t1)
    # frame j's time, frame k's time and k's footprint step from j: matches of revisits
    revisits: list[tuple[float, float, FootStep]] = field(default_factory=list)
    _seen: list[tuple[bytes, NDArray[np.float64]]] = field(default_factory=list)
    _last: tuple[NDArray[np.uint8], NDArray[np.float64]] | None = None  # image, camera px pose
    _model: tuple[CameraModel, float] | None = None
    _differences: list[NDArray[np.float64]] = field(default_factory=list)
    _run_start: int = 0  # the first frame linked to the newest by consecutive pairs

    def add(
        self,
        image: NDArray[np.uint8],
        t: float,
        robot_pose: NDArray[np.float64],
        follows: bool = True,
        encoded: bytes | None = None,
    ) -> None:
        """Frame ``image`` (H, W grey) taken at ``t`` where the odometry put the robot
        (x, y, yaw), registered to the frame before it unless frames between them were
        skipped (``follows`` False: consecutive frames overlap by a third, every other one
        not at all). A registration whose shift is off the odometry's by more than this
        route's registrations are (three robust deviations of their differences, once five
        are known) is a false match and left out. ``encoded``: the image as it came (PNG
        or JPEG), kept for registering a lane passed again (compressed when not given)."""
        import cv2

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
            predicted = relative_se2(last_pose, pose)
            if follows and last.shape == image.shape:
                delta = frame_deltas([last, image], [predicted])[0]
            if delta is not None and not self._agrees(delta - predicted):
                delta = None
            self.deltas.append(delta)
            if delta is None:
                self._run_start = len(self.times)  # this frame starts a new linked run
        if encoded is None:
            encoded = cv2.imencode(".png", image)[1].tobytes()
        self._revisit(image, t, pose, encoded)
        self.times.append(t)
        self._last = image, pose

    def _revisit(
        self, image: NDArray[np.uint8], t: float, pose: NDArray[np.float64], encoded: bytes
    ) -> None:
        """Register ``image`` to the earlier frame the odometry says overlaps it most, of
        those before the chain's last break (the chain itself ties it to those after), if
        as much as the stitcher registers, and keep the match as a revisit. The frames are
        kept as they came (``encoded``: compressed), the last ``KEPT`` of them."""
        import cv2

        from processing.mapping.frame_pairs import frame_deltas
        from processing.stitching.registration import RegistrationParams

        h, w = image.shape
        best: tuple[float, int] | None = None  # (overlap, frame)
        first = len(self.times) - len(self._seen)  # the frame the oldest kept one is
        for j in range(first, self._run_start):
            seen_pose = self._seen[j - first][1]
            # the share of the image both see, as the odometry places them (turned a
            # quarter or half turn, or not at all: the lanes of a sweep)
            x, y, _ = relative_se2(seen_pose, pose)
            overlap = max(0.0, w - abs(x)) * max(0.0, h - abs(y)) / (w * h)
            if best is None or overlap > best[0]:
                best = overlap, j
        if best is not None and best[0] >= RegistrationParams().min_overlap and self._model:
            data, seen_pose = self._seen[best[1] - first]
            seen = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
            if seen is not None and seen.shape == image.shape:
                delta = frame_deltas([seen, image], [relative_se2(seen_pose, pose)])[0]
                model, height_m = self._model
                times = np.array([0.0, 1.0])
                step = planar_factors([delta], times, times, model, height_m).steps[0]
                if step is not None:
                    self.revisits.append((self.times[best[1]], t, step))
        self._seen = [*self._seen[-(KEPT - 1) :], (encoded, pose)]

    def _agrees(self, difference: NDArray[np.float64]) -> bool:
        """Whether a registration's ``difference`` from the odometry's motion (px, px, rad)
        shifts the frame like this route's others do (kept when it does; the turn is left
        alone: the odometry's heading errs most in the turns)."""
        seen = np.array(self._differences[-50:]).reshape(-1, 2)
        if len(seen) >= 5:
            median = np.median(seen, axis=0)
            scatter = 1.4826 * np.median(np.abs(seen - median), axis=0)
            # at least a pixel: the registration's own error
            if (np.abs(difference[:2] - median) > 3 * np.maximum(scatter, 1.0)).any():
                return False
        self._differences.append(difference[:2])
        return True

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

    def relative(self, t0: float, t1: float) -> NDArray[np.float64] | None:
        """The ToF's motion (4, 4) from ``t0`` to ``t1`` as the camera's steps make it,
        along the surface (no change of height or tilt); None where they do not link them
        yet (:meth:`~processing.mapping.camera_motion.CameraFactors.guided`)."""
        from processing.mapping.camera_motion import along_surface

        step = self.step(t0, t1)
        if step is None or self._model is None:
            return None
        return along_surface(step.delta, self._model[0].T_tof_camera)

    def _between(self, t0: float, t1: float) -> FootStep | None:
        """The footprint step from ``t0`` to ``t1``, either way round."""
        if t0 == t1:
            return FootStep(np.zeros(3), np.diag([1e-12, 1e-12, 1e-12]))
        if t0 < t1:
            return self.step(t0, t1)
        back = self.step(t1, t0)
        return None if back is None else FootStep(relative_se2(back.delta, np.zeros(3)), back.cov)

    def loops(
        self, poses: NDArray[np.float64], cloud_times: NDArray[np.float64]
    ) -> list[tuple[int, int, NDArray[np.float64], NDArray[np.float64]]]:
        """(source, target, T_target_source, information) of each revisit carried along
        the chain to the clouds (at ``cloud_times``, posed ``poses`` (N, 4, 4)) nearest its
        two frames; the revisits are used up, but for those whose frames are yet to come."""
        from processing.mapping.camera_motion import camera_edge
        from processing.poses import compose_se2

        out, still = [], []
        times = np.asarray(cloud_times, np.float64)
        for t_j, t_k, step in self.revisits if len(times) else []:
            a, b = int(np.argmin(np.abs(times - t_j))), int(np.argmin(np.abs(times - t_k)))
            into, out_of = self._between(times[a], t_j), self._between(t_k, times[b])
            if (into is None or out_of is None) and max(times[a], times[b]) > self.times[-1]:
                still.append((t_j, t_k, step))  # its frames have not all come yet
                continue
            if a == b or into is None or out_of is None or self._model is None:
                continue
            delta = compose_se2(compose_se2(into.delta, step.delta), out_of.delta)
            loop = FootStep(delta, into.cov + step.cov + out_of.cov)
            model, height_m = self._model
            X, info = camera_edge(loop, np.linalg.inv(poses[a]) @ poses[b], height_m, model)
            out.append((b, a, X, info))
        self.revisits = still[-WAITING:]
        return out

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
