"""Loss weights of a training crop: the crack's centre line, faint stretches most."""

from __future__ import annotations

import cv2
import numpy as np

from processing.learning.data import centre_line_weights


def _crack(width: int, depth: float) -> tuple[np.ndarray, np.ndarray]:
    gray = np.full((64, 64), 0.6, np.float32)
    truth = np.zeros((64, 64), np.uint8)
    cv2.line(truth, (5, 32), (58, 30), 1, width)
    gray[truth > 0] -= depth
    return gray, truth.astype(np.float32)


def test_the_centre_line_is_weighted_and_the_rest_is_one() -> None:
    gray, truth = _crack(width=5, depth=0.3)
    w = centre_line_weights(gray, truth, centre_weight=2.0)
    heavy = w > 1
    assert heavy.any() and np.all(truth[heavy] > 0)  # only crack pixels are weighted up
    assert heavy.sum() < 0.5 * truth.sum()  # the centre line, not the whole width
    np.testing.assert_array_equal(w[~heavy], 1.0)
    assert np.allclose(w[heavy], 3.0)  # a dark crack: 1 + centre_weight


def test_a_faint_crack_weighs_twice_as_much_on_its_centre_line() -> None:
    gray, truth = _crack(width=1, depth=0.03)
    w = centre_line_weights(gray, truth, centre_weight=2.0)
    assert np.median(w[truth > 0]) == 5.0  # 1 + 2 × (1 + faint)


def test_no_crack_or_no_weight_gives_ones() -> None:
    gray, truth = _crack(width=3, depth=0.3)
    assert np.all(centre_line_weights(gray, truth, 0.0) == 1.0)
    assert np.all(centre_line_weights(gray, np.zeros_like(truth), 2.0) == 1.0)
