"""The camera's steps carried over a stretch where its frames do not register.

A stretch of bare, even paint leaves the downward camera nothing to register: the cloud
steps there (:class:`~.camera_motion.CameraFactors`) are unlinked and, along a plate the
ToF cannot place, only the odometry holds them. A robot drives smoothly, so the steps
either side of such a gap predict the steps inside it: interpolated between the last
linked step before and the first after, each as sure as this route's own steps are
predicted over a gap of the same length (the robust scatter of that interpolation over
every linked stretch, :func:`interpolation_scatter`). Nothing is predicted where the
motion changes across the gap (its two ends disagree by more than the route's steps do
that far apart: a turn begins or ends there) or where the odometry disagrees with the
prediction by more than the odometry's error, measured on the steps the camera linked (a
stop, a turn inside the gap).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from processing.mapping.camera_motion import FootStep
from processing.poses import compose_se2, wrap_angle


@dataclass(frozen=True)
class MotionPriorParams:
    """When the steps either side of a gap are carried over it."""

    enabled: bool = True
    # how many linked stretches of the gap's length the route needs to say how well its
    # steps are predicted (fewer: nothing is predicted)
    min_samples: int = 8
    # the gap's two ends may differ by this many of the route's robust deviations ...
    max_end_change: float = 3.0
    # ... and the prediction from the trajectory by this many of the odometry's errors
    max_odometry_change: float = 3.0


def _steps_array(steps: Sequence[FootStep | None]) -> NDArray[np.float64]:
    return np.array([np.full(3, np.nan) if s is None else s.delta for s in steps]).reshape(-1, 3)


def _difference(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    d[..., 2] = wrap_angle(d[..., 2])
    return d


def _robust_scatter(residuals: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    r = np.array(residuals)
    return 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)


def interpolation_scatter(
    deltas: NDArray[np.float64], length: int, min_samples: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """How a route's steps ``deltas`` (N, 3: x, y m, ψ rad; NaN rows unlinked) behave over
    ``length`` unlinked steps, measured on its linked ones: the robust scatter (3,) of a
    step interpolated between the steps ``length + 1`` apart around it, and of the
    difference between two steps that far apart; None with fewer than ``min_samples``."""
    ok = np.isfinite(deltas[:, 0])
    span = length + 1
    predicted: list[NDArray[np.float64]] = []
    ends: list[NDArray[np.float64]] = []
    for a in np.flatnonzero(ok[: len(ok) - span]):
        b = a + span
        if not ok[b]:
            continue
        ends.append(_difference(deltas[b], deltas[a]))
        for j in range(a + 1, b):
            if ok[j]:
                w = (j - a) / span
                predicted.append(
                    _difference(deltas[j], deltas[a] + w * _difference(deltas[b], deltas[a]))
                )
    if len(predicted) < min_samples or len(ends) < min_samples:
        return None
    return _robust_scatter(predicted), _robust_scatter(ends)


def bridge_gaps(
    steps: Sequence[FootStep | None],
    odometry: NDArray[np.float64] | None = None,
    params: MotionPriorParams = MotionPriorParams(),
) -> tuple[list[FootStep | None], NDArray[np.bool_]]:
    """``steps`` (N - 1 cloud steps, None unlinked) with each gap between two linked steps
    carried over by interpolation where the route's smoothness allows (module docstring),
    and which steps (N - 1,) were so predicted. ``odometry`` (N - 1, 3): the same steps as
    the odometry measured them (NaN rows unknown), as wrong as they prove where the camera
    measured the steps too; without it only the gap's ends are checked."""
    out = list(steps)
    predicted = np.zeros(len(out), bool)
    if not params.enabled:
        return out, predicted
    deltas = _steps_array(steps)
    ok = np.isfinite(deltas[:, 0])
    check = None  # the odometry's steps and their error
    if odometry is not None:
        measured = np.asarray(odometry, np.float64).reshape(-1, 3)
        both = ok & np.isfinite(measured).all(axis=1)
        if both.sum() >= params.min_samples:
            check = measured, _robust_scatter(list(_difference(measured[both], deltas[both])))
    j = 0
    while j < len(out):
        if ok[j]:
            j += 1
            continue
        k = j
        while k < len(out) and not ok[k]:
            k += 1
        a, b = j - 1, k
        if a >= 0 and b < len(out):
            fill = _bridge(deltas, a, b, check, params)
            if fill is not None:
                out[j:k] = fill
                predicted[j:k] = True
        j = k
    return out, predicted


def _bridge(
    deltas: NDArray[np.float64],
    a: int,
    b: int,
    odometry: tuple[NDArray[np.float64], NDArray[np.float64]] | None,
    params: MotionPriorParams,
) -> list[FootStep | None] | None:
    """The steps a + 1 .. b - 1 between linked steps a and b, or None where they cannot be
    predicted; ``odometry``: the odometry's steps (N - 1, 3) and their error (3,)."""
    length = b - a - 1
    scatter = interpolation_scatter(deltas, length, params.min_samples)
    if scatter is None:
        return None
    sigma, end_sigma = scatter
    change = _difference(deltas[b], deltas[a])
    if (np.abs(change) > params.max_end_change * np.maximum(end_sigma, 1e-9)).any():
        return None  # the motion changes across the gap
    fill = [deltas[a] + (m - a) / (length + 1) * change for m in range(a + 1, b)]
    if odometry is not None:
        steps, odometry_sigma = odometry
        along, measured = np.zeros(3), np.zeros(3)
        for m, step in zip(range(a + 1, b), fill):
            along, measured = compose_se2(along, step), compose_se2(measured, steps[m])
        var = length * (odometry_sigma**2 + sigma**2)
        off = np.abs(_difference(along, measured)) / np.sqrt(np.maximum(var, 1e-18))
        if not np.isfinite(off).all() or (off > params.max_odometry_change).any():
            return None  # a stop or a turn inside the gap (or no odometry to tell)
    # the steps of one gap err together (the robot's speed changed): each as sure as the
    # interpolation over the gap's length, its sum as sure as that times the gap's length
    cov = np.diag(length * np.maximum(sigma, 1e-9) ** 2)
    return [FootStep(np.asarray(d, np.float64), cov) for d in fill]


def trajectory_feet(
    poses: NDArray[np.float64], T_tof_camera: NDArray[np.float64], distances_m: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(N - 1, 3) footprint steps of the camera between consecutive ToF ``poses`` (N, 4, 4),
    at the surface ``distances_m`` (N,)."""
    from processing.mapping.camera_motion import foot

    T_tc = np.asarray(T_tof_camera, np.float64)
    cams = np.asarray(poses, np.float64) @ T_tc
    return np.array(
        [
            foot(np.linalg.inv(cams[i]) @ cams[i + 1], float(distances_m[i]))
            for i in range(len(cams) - 1)
        ]
    ).reshape(-1, 3)
