import numpy as np
import pytest

from processing.poses import compose_se2, relative_se2, wrap_angle
from processing.stitching.alignment import BLIND_ANGLES
from processing.stitching.exposure import solve_gains
from processing.stitching.pose_graph import solve_pose_graph
from processing.stitching.registration import Level, PairMeasurement, register_pair
from tests.processing.helpers import frame_at, texture


@pytest.mark.parametrize("turn", [0.0, np.pi])
def test_register_pair_recovers_rotation_and_translation_to_a_hundredth_of_a_pixel(
    turn: float,
) -> None:
    tex = texture(4)
    a = np.array([500.0, 400.0, 0.01])
    b = np.array([707.3, 391.6, turn - 0.025])
    true = relative_se2(a, b)
    guess = true + np.array([9.0, -7.0, 0.004])  # odometry-sized error
    found = register_pair(frame_at(tex, a), frame_at(tex, b), guess)
    assert found is not None
    delta, score, _, _ = found
    assert score > 0.95
    assert np.abs(delta[:2] - true[:2]).max() < 0.05
    assert abs(float(wrap_angle(delta[2] - true[2]))) < 2e-4


@pytest.mark.parametrize("turn_deg", [-3.6, -1.1, 2.9])
def test_register_pair_finds_an_unknown_turn_among_the_search_angles(turn_deg: float) -> None:
    """Images only: the guess (phase correlation) knows no rotation; the coarse search
    picks the best of the search angles (climbing at a quarter of the resolution on
    640x480 frames) and the refinement reaches the exact turn."""
    tex = texture(8, (1200, 1800))
    size = (640, 480)
    a = np.array([600.0, 600.0, 0.0])
    b = np.array([1010.0, 596.0, np.radians(turn_deg)])
    true = relative_se2(a, b)
    guess = np.array([true[0] + 6.0, true[1] - 5.0, 0.0])
    found = register_pair(
        frame_at(tex, a, size), frame_at(tex, b, size), guess, angles=BLIND_ANGLES
    )
    assert found is not None
    assert np.abs(found[0][:2] - true[:2]).max() < 0.05
    assert abs(float(wrap_angle(found[0][2] - true[2]))) < 2e-4


def test_register_pair_refuses_frames_that_do_not_overlap_or_have_no_texture() -> None:
    tex = texture(5)
    a, b = np.array([300.0, 300.0, 0]), np.array([900.0, 300.0, 0])
    assert register_pair(frame_at(tex, a), frame_at(tex, b), relative_se2(a, b)) is None
    flat = np.full((240, 320), 90, np.float32)
    assert register_pair(flat, flat, np.array([200.0, 0, 0])) is None


def test_levels_are_reusable_across_pairs() -> None:
    tex = texture(6)
    poses = [np.array([400.0 + 200 * k, 400.0, 0]) for k in range(3)]
    levels = [Level.of(frame_at(tex, p)) for p in poses]
    for i, j in ((0, 1), (1, 2)):
        found = register_pair(levels[i], levels[j], relative_se2(poses[i], poses[j]) + (3, 2, 0))
        assert (
            found is not None
            and np.abs(found[0][:2] - relative_se2(poses[i], poses[j])[:2]).max() < 0.05
        )


def test_pose_graph_spreads_a_loop_closure_instead_of_drifting() -> None:
    rng = np.random.default_rng(0)
    truth = np.array(
        [[200.0 * k, 0.0, 0.0] for k in range(6)]
        + [[200.0 * (5 - k), 150.0, np.pi] for k in range(6)]
    )
    meas = []
    for i, j in [(k, k + 1) for k in range(11)] + [(k, 11 - k) for k in range(6)]:
        delta = (
            relative_se2(truth[i], truth[j]) + np.r_[rng.normal(0, 0.05, 2), rng.normal(0, 1e-4)]
        )
        meas.append(PairMeasurement(i, j, delta, 1.0, 100.0, 100.0))
    # a start that has drifted 30 px and 2°
    start = [truth[0]]
    for k in range(11):
        start.append(
            compose_se2(
                start[-1], relative_se2(truth[k], truth[k + 1]) + np.array([3.0, 2.0, 0.003])
            )
        )
    solved = solve_pose_graph(np.array(start), meas, None)
    assert np.allclose(solved[0], truth[0])  # the gauge stays put
    assert np.abs(solved[:, :2] - truth[:, :2]).max() < 0.5


def test_pose_graph_holds_unmeasured_frames_by_their_priors() -> None:
    truth = np.array([[0.0, 0, 0], [200, 0, 0], [400, 0, 0]])
    priors = np.array([relative_se2(truth[0], truth[1]), relative_se2(truth[1], truth[2])])
    meas = [PairMeasurement(0, 1, priors[0] + (0.5, 0, 0), 1.0, 1, 1)]
    solved = solve_pose_graph(truth.copy(), meas, priors)
    assert solved[1, 0] == pytest.approx(200.5, abs=0.01)
    assert solved[2, 0] == pytest.approx(400.5, abs=0.01)  # moved with its neighbour


def test_gains_equalise_overlap_brightness() -> None:
    true = np.array([1.0, 1.25, 0.8, 1.1])
    meas = [
        PairMeasurement(k, k + 1, np.zeros(3), 1.0, 100 * true[k], 100 * true[k + 1])
        for k in range(3)
    ]
    g = solve_gains(4, meas, sigma_g=10.0)
    fixed = g * true
    assert fixed.std() / fixed.mean() < 0.01
