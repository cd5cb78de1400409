"""Wheel odometry from the MCU's Hall edge counts (paper §2.1: magnets on each wheel)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from processing.poses import integrate_arc, wheel_turn, wrap_angle


@dataclass
class HallOdometry:
    """Planar pose (x, y, θ) integrated from cumulative edge counts of the four wheels
    (FL, FR, RL, RR); ``distance_m`` is the path length driven (turning in place adds none)."""

    metres_per_edge: float
    track_m: float
    pose: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    distance_m: float = 0.0
    _last: NDArray[np.int64] | None = None

    def update(self, hall: tuple[int, int, int, int]) -> float:
        """Advance with a new count sample; the distance moved since the last one."""
        counts = np.asarray(hall, np.int64)
        if self._last is None:
            self._last = counts
            return 0.0
        delta = (counts - self._last) * self.metres_per_edge
        self._last = counts
        left, right = float(delta[[0, 2]].mean()), float(delta[[1, 3]].mean())
        d = (left + right) / 2
        self.pose = integrate_arc(self.pose, d, wheel_turn(left, right, self.track_m))
        self.distance_m += abs(d)
        return abs(d)

    def set_heading(self, heading: float) -> None:
        """Correct the heading (after squaring up to a known edge)."""
        self.pose[2] = float(wrap_angle(heading))

    def as_meta(self) -> dict[str, float]:
        """The pose for the wire."""
        return {"x": float(self.pose[0]), "y": float(self.pose[1]), "yaw": float(self.pose[2])}
