"""The camera's steps carried over a stretch its frames did not register: predicted from the
steps either side where the route drives smoothly, never across a change of motion or
against the odometry, and the map held to millimetres across such a stretch."""

import numpy as np

from processing.mapping import register_clouds
from processing.mapping.camera_motion import CameraFactors, FootStep
from processing.mapping.motion_prior import MotionPriorParams, bridge_gaps, interpolation_scatter
from processing.metrics import absolute_trajectory_error
from processing.poses import compose_se2


def _route(n: int, seed: int = 0, turn_from: int | None = None) -> np.ndarray:
    """(n, 3) footprint steps of a robot driving 50 mm a step, each a little off (the
    robot's rocking), turning 30° a step from ``turn_from`` on."""
    rng = np.random.default_rng(seed)
    steps = np.tile([0.05, 0.0, 0.0], (n, 1)) + rng.normal(0, [5e-4, 3e-4, 2e-3], (n, 3))
    if turn_from is not None:
        steps[turn_from:, 2] += np.radians(30)
    return steps


def _steps(deltas: np.ndarray, gap: range) -> list[FootStep | None]:
    cov = np.diag([1e-8, 1e-8, 1e-6])
    return [None if k in gap else FootStep(d, cov) for k, d in enumerate(deltas)]


def test_a_gap_on_a_smooth_route_is_carried_as_sure_as_the_route_predicts_itself() -> None:
    truth = _route(40)
    filled, predicted = bridge_gaps(_steps(truth, range(12, 16)), truth)
    assert list(np.flatnonzero(predicted)) == [12, 13, 14, 15]
    for k in range(12, 16):
        step = filled[k]
        assert step is not None
        error = np.abs(step.delta - truth[k])
        # within three of its own deviations, which are millimetres, not the odometry's
        assert (error < 3 * np.sqrt(np.diag(step.cov))).all(), (error, step.cov)
        assert np.sqrt(step.cov[0, 0]) < 3e-3
    # a step's own jitter (0.5 mm) and its two ends': about 1.2-1.4 times the jitter
    scatter = interpolation_scatter(truth, 4, 8)
    assert scatter is not None and 5e-4 < scatter[0][0] < 1.5e-3


def test_nothing_is_carried_across_a_change_of_motion_or_against_the_odometry() -> None:
    turning = _route(40, turn_from=14)
    _, predicted = bridge_gaps(_steps(turning, range(12, 16)), turning)
    assert not predicted.any()  # a turn begins inside the gap
    straight = _route(40)
    stopped = straight.copy()
    stopped[12:16] = 0.0  # the robot stood still where the frames did not register
    _, predicted = bridge_gaps(_steps(straight, range(12, 16)), stopped)
    assert not predicted.any()
    # without the odometry only the ends are checked: a smooth route is carried
    _, predicted = bridge_gaps(_steps(straight, range(12, 16)))
    assert predicted[12:16].all()


def test_gaps_at_the_ends_and_routes_too_short_to_tell_are_left_alone() -> None:
    truth = _route(40)
    filled, predicted = bridge_gaps(_steps(truth, range(0, 3)), truth)
    assert not predicted.any() and filled[0] is None
    short = _route(6)
    _, predicted = bridge_gaps(_steps(short, range(2, 4)), short)
    assert not predicted.any()
    _, predicted = bridge_gaps(
        _steps(truth, range(12, 16)), truth, MotionPriorParams(enabled=False)
    )
    assert not predicted.any()


def test_the_map_is_held_across_a_stretch_the_frames_did_not_register(
    sequence, sequence_factors
) -> None:  # type: ignore[no-untyped-def]
    sweep, _, shape = sequence
    factors = sequence_factors
    model = factors.camera
    # five steps of the second lane unregistered (bare paint)
    gapped = CameraFactors(
        model,
        [None if 24 <= k < 29 else s for k, s in enumerate(factors.steps)],
        factors.distances_m,
        factors.scale_sigma,
    )

    def ate(motion: MotionPriorParams) -> tuple[float, np.ndarray]:
        result = register_clouds(
            sweep.clouds, sweep.odometry, shape=shape, camera=gapped, motion=motion
        )
        return absolute_trajectory_error(result.poses, sweep.truth), result.motion_steps

    carried, steps = ate(MotionPriorParams())
    left, _ = ate(MotionPriorParams(enabled=False))
    assert steps[25:30].all() and not steps[:6].any()
    assert carried < 0.3 * left and 100 * carried / sweep.path_length_m < 0.2
    # a turn inside the gap: not carried
    turning = CameraFactors(
        model,
        [None if 10 <= k < 16 else s for k, s in enumerate(factors.steps)],
        factors.distances_m,
    )
    result = register_clouds(sweep.clouds, sweep.odometry, shape=shape, camera=turning)
    assert not result.motion_steps[11:17].any()


def test_compose_of_carried_steps_is_the_interpolated_motion() -> None:
    truth = _route(30, seed=3)
    filled, predicted = bridge_gaps(_steps(truth, range(10, 13)), truth)
    assert predicted[10:13].all()
    along = np.zeros(3)
    for k in range(10, 13):
        step = filled[k]
        assert step is not None
        along = compose_se2(along, step.delta)
    true_along = np.zeros(3)
    for k in range(10, 13):
        true_along = compose_se2(true_along, truth[k])
    assert np.abs(along - true_along)[:2].max() < 3e-3
