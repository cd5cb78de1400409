"""The error model of the pose graph's odometry edges: a step's configured error, how much
larger the odometry's error proves than configured, and an edge's information."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from processing.mapping.params import OdometryParams
from processing.mapping.tracking import axis_information


def odometry_sigma(step: NDArray[np.float64], params: OdometryParams) -> tuple[float, float]:
    """Configured error of an odometry ``step`` (4, 4): rotation (rad) and translation (m),
    growing with the step's length."""
    d = float(np.linalg.norm(step[:3, 3]))
    return float(np.radians(params.sigma_deg_per_m * d + 0.2)), max(
        params.sigma_frac * d, params.sigma_floor_m
    )


def odometry_error_scale(heading_gaps: Sequence[float], params: OdometryParams) -> float:
    """How much larger the odometry's heading error is than configured (>= 1): the robust
    spread (1.4826 MAD) of its heading steps against ICP's, where the structure fixes
    them, each over its configured error (``heading_gaps``); 1 until 10 such steps were
    seen. ICP's own error is in the spread, so odometry as good as configured stays at 1."""
    if not params.calibrate or len(heading_gaps) < 10:
        return 1.0
    return max(1.0, 1.4826 * float(np.median(np.abs(heading_gaps))))


def odometry_information(
    sigma: tuple[float, float] | None,
    tracked_information: NDArray[np.float64] | None,
    wheels: bool,
    scale: float,
) -> NDArray[np.float64]:
    """Information of a cloud's odometry edge: once a wheel model holds the steps
    (``wheels``), its tracked pose's (``tracked_information``: the geometry's where it
    observes, the prediction's elsewhere), else its configured odometry errors ``sigma``
    (rotation rad, translation m) times ``scale``."""
    if wheels and tracked_information is not None:
        return tracked_information
    assert sigma is not None
    sigma_r, sigma_t = sigma
    return axis_information(scale * sigma_r, scale * sigma_t)
