import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from processing.metrics import (
    Box,
    absolute_trajectory_error,
    account_defects,
    match_defects,
    segmentation_scores,
)


def test_pi_si_dsc_on_a_hand_made_case() -> None:
    truth = np.zeros((4, 4), bool)
    truth[0, :] = True  # 4 true pixels
    pred = np.zeros((4, 4), bool)
    pred[0, :2] = True  # 2 TP
    pred[3, 3] = True  # 1 FP
    s = segmentation_scores(pred, truth)
    assert s.pi == pytest.approx(2 / 3) and s.si == pytest.approx(0.5)
    assert s.dsc == pytest.approx(2 * 2 / (2 * 2 + 1 + 2))


def test_tolerance_forgives_one_pixel_offsets() -> None:
    truth = np.zeros((20, 20), bool)
    truth[10, 2:18] = True
    pred = np.roll(truth, 1, axis=0)
    assert segmentation_scores(pred, truth).dsc == 0
    assert segmentation_scores(pred, truth, tolerance_px=2).dsc == pytest.approx(1)


def test_ate_is_zero_for_a_rigidly_moved_copy_and_positive_for_noise() -> None:
    rng = np.random.default_rng(0)
    gt = np.repeat(np.eye(4)[None], 20, axis=0)
    gt[:, :3, 3] = np.cumsum(rng.normal(size=(20, 3)) * 0.1, axis=0)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [0.1, -0.2, 0.3]).as_matrix()
    T[:3, 3] = (1, 2, 3)
    moved = T @ gt
    assert absolute_trajectory_error(moved, gt) == pytest.approx(0, abs=1e-9)
    noisy = gt.copy()
    noisy[:, :3, 3] += rng.normal(size=(20, 3)) * 0.01
    assert 0.005 < absolute_trajectory_error(noisy, gt) < 0.03


def test_defect_matching_needs_the_same_class_and_overlap() -> None:
    truth = [Box("crack", 0, 0, 0.1, 0.01), Box("corrosion", 1, 1, 0.05, 0.05)]
    found = [Box("crack", 0.05, 0.005, 0.1, 0.01), Box("crack", 1, 1, 0.05, 0.05)]
    assert match_defects(found, truth) == 1


def test_found_defects_are_told_apart_as_hits_pieces_and_false_alarms() -> None:
    truth = [Box("crack", 0, 0, 0.2, 0.01), Box("corrosion", 1, 1, 0.05, 0.05)]
    found = [
        Box("crack", 0.0, 0.0, 0.08, 0.01),  # first half of the crack
        Box("crack", 0.12, 0.0, 0.08, 0.01),  # its second half: a piece
        Box("crack", 0.5, 0.5, 0.05, 0.01),  # nothing there: a false alarm
        Box("crack", 1, 1, 0.05, 0.05),  # on the rust, but not rust: a false alarm
    ]
    acc = account_defects(found, truth)
    assert (acc.found, acc.true, acc.matched) == (4, 2, 1)
    assert (acc.on_true, acc.pieces, acc.false_alarms) == (2, 1, 2)
    assert acc.precision == 0.5 and acc.recall == 0.5
    none = account_defects([], truth)
    assert none.precision == 1.0 and none.recall == 0.0


def test_a_merge_does_not_hide_a_crack_found_in_pieces() -> None:
    truth = [Box("crack", 0, 0, 0.1, 0.01), Box("crack", 0.1, 0, 0.1, 0.01)]
    truth.append(Box("crack", 0, 1, 0.2, 0.01))
    found = [
        Box("crack", 0, 0, 0.2, 0.01),  # one box over the first two cracks
        Box("crack", 0, 1, 0.09, 0.01),  # the third crack in two pieces
        Box("crack", 0.11, 1, 0.09, 0.01),
    ]
    acc = account_defects(found, truth)
    assert (acc.matched, acc.on_true, acc.pieces, acc.false_alarms) == (3, 3, 1, 0)
