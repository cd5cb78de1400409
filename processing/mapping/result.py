"""What a map comes to: the registered poses, the fused points, and what each cloud's
registration and the graph did."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from processing.mapping.camera_mounting import MountingFit


@dataclass
class MapResult:
    """Registered poses T_world_sensor (N, 4, 4), the fused map (M, 3) and per-cloud facts."""

    poses: NDArray[np.float64]
    points: NDArray[np.float32]
    fitness: NDArray[np.float64]
    rmse: NDArray[np.float64]
    used_odometry: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    degenerate_dims: NDArray[np.int_] = field(default_factory=lambda: np.zeros(0, int))
    loop_closures: int = 0
    pruned_edges: int = 0
    # the odometry's error measured against ICP, over the configured one (>= 1)
    odometry_error_scale: float = 1.0
    # large planes (deck plate, web, stiffener faces) that tied the clouds seeing them
    plane_landmarks: int = 0
    # clouds tied to the one before by the downward camera's motion
    camera_steps: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    # clouds tied to the one before by the camera's steps either side of a stretch its
    # frames did not register (:mod:`processing.mapping.motion_prior`)
    motion_steps: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    # the camera's mounting checked against the ToF's motion (None: not checked)
    camera_mounting: MountingFit | None = None
