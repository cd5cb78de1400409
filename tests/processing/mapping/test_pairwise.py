import numpy as np
import pytest

from processing.mapping import (
    MapParams,
    TrackingParams,
    measure_run,
    register_clouds,
    register_measured,
)
from robot_link.sim.tof_sweeps import TofSweepConfig, tof_sweep

PAIRWISE = MapParams(tracking=TrackingParams(enabled=False))


def test_runs_measured_apart_join_into_the_map_of_the_whole_session() -> None:
    sweep = tof_sweep(TofSweepConfig(seed=13))
    shape = (int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"]))
    whole = register_clouds(sweep.clouds, sweep.odometry, params=PAIRWISE, shape=shape)
    n, context = len(sweep.clouds), PAIRWISE.neighbours
    measured = []
    for first in range(0, n, 17):  # runs of unequal length, each from its own start
        start = max(0, first - context)
        last = min(first + 17, n)
        run = measure_run(
            sweep.clouds[start:last],
            sweep.odometry[start:last],
            first,
            first - start,
            PAIRWISE,
            shape,
        )
        assert len(run) == last - first
        measured.extend(run)
    joined = register_measured(measured, sweep.odometry, params=PAIRWISE)
    assert joined.loop_closures == whole.loop_closures > 0
    assert joined.plane_landmarks == whole.plane_landmarks
    np.testing.assert_allclose(joined.poses, whole.poses, atol=1e-6)
    np.testing.assert_array_equal(joined.degenerate_dims, whole.degenerate_dims)
    assert joined.odometry_error_scale == pytest.approx(whole.odometry_error_scale)


def test_measured_clouds_need_one_odometry_pose_each_and_no_tracking() -> None:
    sweep = tof_sweep(
        TofSweepConfig(seed=13, x_range_m=(0.15, 0.4), lanes_y_m=(0.6,), revisit=False)
    )
    measured = measure_run(sweep.clouds, sweep.odometry, 0, 0, PAIRWISE)
    with pytest.raises(ValueError, match="one odometry pose per measured cloud"):
        register_measured(measured, sweep.odometry[:-1], params=PAIRWISE)
    with pytest.raises(ValueError, match="without tracking"):
        register_measured(measured, sweep.odometry)


def test_runs_measured_apart_join_with_the_camera_as_the_whole_session_does(
    sequence, sequence_factors
) -> None:  # type: ignore[no-untyped-def]
    sweep, _, shape = sequence
    factors = sequence_factors
    whole = register_clouds(
        sweep.clouds, sweep.odometry, params=PAIRWISE, shape=shape, camera=factors
    )
    n, context = len(sweep.clouds), PAIRWISE.neighbours
    starts = factors.guided(sweep.odometry, n)  # as register_clouds starts its clouds
    measured = []
    for first in range(0, n, 17):
        start = max(0, first - context)
        last = min(first + 17, n)
        measured.extend(
            measure_run(
                sweep.clouds[start:last], starts[start:last], first, first - start, PAIRWISE, shape
            )
        )
    joined = register_measured(measured, sweep.odometry, params=PAIRWISE, camera=factors)
    np.testing.assert_allclose(joined.poses, whole.poses, atol=1e-6)
    np.testing.assert_array_equal(joined.camera_steps, whole.camera_steps)
    np.testing.assert_array_equal(joined.motion_steps, whole.motion_steps)
    assert joined.camera_steps.sum() > n // 2
