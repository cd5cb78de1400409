"""Fitting the per-defect confidence: labels from the truth, a logistic fit that recovers a
known model, and a clear error when there is nothing to fit."""

from __future__ import annotations

import numpy as np
import pytest

from processing.detection.confidence import reliability
from processing.learning.calibration import fit_calibration, labelled_components


def test_a_component_on_the_truth_is_true_and_one_off_it_is_false() -> None:
    truth = np.zeros((50, 50), bool)
    truth[10, 5:40] = True
    prob = np.full((50, 50), 0.01, np.float32)
    prob[11, 5:40] = 0.9  # one pixel beside the labelled line: within the tolerance
    prob[30:33, 20:26] = 0.8  # nothing there
    feats, labels = labelled_components(prob, truth, threshold=0.5)
    assert feats.shape == (2, 2)
    order = np.argsort(feats[:, 1])  # the smaller (18 px) one is the false one
    assert labels[order].tolist() == [False, True]
    empty = labelled_components(np.zeros((10, 10), np.float32), truth[:10, :10], 0.5)
    assert empty[0].shape == (0, 2) and empty[1].shape == (0,)


def test_the_fit_recovers_a_known_logistic_model_and_is_calibrated() -> None:
    rng = np.random.default_rng(1)
    x = np.column_stack([rng.normal(1.0, 2.0, 4000), rng.normal(3.0, 1.0, 4000)])
    true_p = 1 / (1 + np.exp(-(0.8 * x[:, 0] + 1.2 * x[:, 1] - 4.0)))
    y = rng.uniform(size=len(true_p)) < true_p
    cal = fit_calibration(x, y)
    np.testing.assert_allclose(cal.coef, (0.8, 1.2), atol=0.15)
    assert cal.intercept == pytest.approx(-4.0, abs=0.5)
    assert reliability(cal.confidence(x), y)[0] < 0.03


def test_too_few_or_one_sided_components_are_refused() -> None:
    with pytest.raises(ValueError, match="both kinds"):
        fit_calibration(np.zeros((5, 2)), np.array([True, False, True, False, True]))
    with pytest.raises(ValueError, match="both kinds"):
        fit_calibration(np.zeros((50, 2)), np.ones(50, bool))
