"""The odometry's quaternion order told by the clouds, on simulated ToF sweeps."""

import numpy as np
import pytest

from processing.mapping.quaternion_order import check_order
from processing.poses import format_tum, poses_of_tum_rows, tum_rows
from robot_link.sim.tof_sweeps import TofSweepConfig, tof_sweep


@pytest.mark.parametrize("seed", [71, 72])
def test_the_clouds_tell_a_w_first_file_from_a_right_one(seed: int) -> None:
    sweep = tof_sweep(TofSweepConfig(seed=seed))
    rows = tum_rows(format_tum(np.arange(len(sweep.odometry), dtype=float), sweep.odometry))
    right = check_order(
        sweep.clouds, poses_of_tum_rows(rows), poses_of_tum_rows(rows, w_first=True)
    )
    assert not right.swap and right.ratio < 0.5
    written_w_first = rows.copy()
    written_w_first[:, 4:] = np.roll(rows[:, 4:], 1, axis=1)
    wrong = check_order(
        sweep.clouds,
        poses_of_tum_rows(written_w_first),
        poses_of_tum_rows(written_w_first, w_first=True),
    )
    assert wrong.swap and wrong.ratio > 2
