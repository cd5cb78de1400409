"""A calibrated confidence per found crack: its features, its fit and its reliability."""

from __future__ import annotations

import numpy as np
import pytest

from processing.detection.confidence import (
    Calibration,
    component_features,
    logit_code,
    probability_of_code,
    reliability,
)
from processing.detection.defects import measure_defects


def _logit(p: float) -> float:
    return float(np.log(p / (1 - p)))


def test_features_are_the_mean_logit_and_log_size_of_each_component() -> None:
    prob = np.full((20, 30), 0.01, np.float32)
    labels = np.zeros((20, 30), np.int32)
    labels[2:4, 2:12] = 1  # 20 pixels at 0.9
    prob[2:4, 2:12] = 0.9
    labels[10, 5:9] = 2  # 4 pixels, half 0.6 half 0.99
    prob[10, 5:7], prob[10, 7:9] = 0.6, 0.99
    f = component_features(prob, labels, 3)
    np.testing.assert_allclose(f[0], 0.0)
    np.testing.assert_allclose(f[1], [_logit(0.9), np.log(20)], rtol=1e-5)
    np.testing.assert_allclose(f[2], [(_logit(0.6) + _logit(0.99)) / 2, np.log(4)], rtol=1e-5)
    with pytest.raises(ValueError, match="differ"):
        component_features(prob, labels[:10], 3)


def test_stored_logit_codes_give_the_probability_back_within_a_step() -> None:
    p = np.linspace(0.001, 0.999, 1000).astype(np.float32)
    back = probability_of_code(logit_code(p))
    z, zb = np.log(p / (1 - p)), np.log(back / (1 - back))
    assert np.max(np.abs(z - zb)) <= 8 / 255 + 1e-4  # half a code step


def test_reliability_of_a_calibrated_and_an_overconfident_detector() -> None:
    rng = np.random.default_rng(0)
    conf = rng.uniform(0, 1, 20000)
    honest = rng.uniform(0, 1, conf.size) < conf
    ece, rows = reliability(conf, honest)
    assert ece < 0.02 and len(rows) == 10
    assert all(abs(r["confidence"] - r["true"]) < 0.05 for r in rows)
    overconfident = rng.uniform(0, 1, conf.size) < 0.5  # says 0–1, is right half the time
    assert reliability(conf, overconfident)[0] > 0.2
    assert reliability(np.zeros(0), np.zeros(0, bool)) == (0.0, [])


def test_the_record_keeps_the_calibration_and_a_model_without_one_has_none() -> None:
    cal = Calibration((1.5, 0.4), -2.0)
    assert Calibration.from_record({"calibration": cal.to_record()}) == cal
    assert Calibration.from_record({}) is None
    assert Calibration.from_record({"calibration": {"features": ["other"]}}) is None
    np.testing.assert_allclose(cal.confidence(np.array([[0.0, 5.0]])), [0.5])


def test_each_measured_crack_gets_the_confidence_of_its_own_pixels() -> None:
    mask = np.zeros((40, 60), bool)
    mask[5, 5:45] = True  # a long crack the network is sure of
    mask[30, 10:13] = True  # a speck it is not
    prob = np.where(mask, 0.55, 0.01).astype(np.float32)
    prob[5, 5:45] = 0.98
    cal = Calibration((1.0, 1.0), -4.0)
    found = measure_defects(mask, "crack", probability=prob, calibration=cal)
    by_row = {d.bbox[1]: d.confidence for d in found}
    expected_long = 1 / (1 + np.exp(-(_logit(0.98) + np.log(40) - 4)))
    assert by_row[5] == pytest.approx(expected_long, abs=1e-3)
    assert by_row[30] < 0.2 < by_row[5]
    assert all(d.confidence is None for d in measure_defects(mask, "crack"))  # no network
