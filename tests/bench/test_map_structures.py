"""The structure benchmark's registration floor: each cloud registered to a perfect map."""

import numpy as np

from bench.map_structures import registration_floor
from processing.metrics import absolute_trajectory_error
from robot_link.sim.scene_sweeps import SceneSweepConfig, scene_sweep


def _floor(sweep, odometry: np.ndarray) -> np.ndarray:
    shape = (int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"]))
    return registration_floor(sweep.clouds, sweep.truth, odometry, shape, (np.radians(2.0), 0.02))


def test_the_floor_fixes_what_the_view_sees_and_nothing_drifts() -> None:
    """On a box girder the floor is far below odometry alone; from exact odometry it stays
    within millimetres of the truth (the map is the truth: nothing to drift from)."""
    sweep = scene_sweep(SceneSweepConfig(kind="box_girder", seed=3, clouds=16))
    floor = _floor(sweep, sweep.odometry)
    assert floor.shape == sweep.truth.shape
    assert absolute_trajectory_error(floor, sweep.truth) < 0.25 * absolute_trajectory_error(
        sweep.odometry, sweep.truth
    )
    exact = _floor(sweep, sweep.truth)
    assert absolute_trajectory_error(exact, sweep.truth) < 0.003
