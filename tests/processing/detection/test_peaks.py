import numpy as np
import pytest

from processing.detection.peaks import (
    crossover_indices,
    dominant_peaks,
    initial_peaks,
    offset_distances,
    smooth_histogram,
    valley_emphasis_threshold,
)


def test_eq3_three_tap_moving_average() -> None:
    h = np.array([0, 3, 0, 0, 6, 0], float)
    s = smooth_histogram(h)
    assert s[1] == pytest.approx(1.0) and s[4] == pytest.approx(2.0) and s[3] == pytest.approx(2.0)
    assert s.sum() == pytest.approx(h.sum() + (h[0] + h[-1]) / 3)  # edges replicated
    with pytest.raises(ValueError, match="hist"):
        smooth_histogram(np.zeros(2))


def test_eq4_initial_peaks_are_strict_local_maxima() -> None:
    h = np.array([1, 5, 2, 2, 7, 7, 3, 4, 1], float)
    assert list(initial_peaks(h)) == [1, 4, 7]


def test_eq6_offset_distance_and_eq8_crossover_index_by_hand() -> None:
    h = np.zeros(20)
    h[[4, 10, 16]] = [10, 40, 20]
    delta = np.array([4, 10, 16])
    L = offset_distances(h, delta)
    assert L[0] == pytest.approx(10 * 6 / 30)  # h(δ1)[g(δ2)-g(δ1)] / |h(δ2)-h(δ1)|
    assert L[1] == pytest.approx(40 * 6 / 20)
    assert L[2] == pytest.approx(20 * 6 / 20)  # last peak: its left neighbour
    h_eq = h.copy()
    h_eq[10] = 10  # equal heights: (k+1)/k factor, k = 1
    assert offset_distances(h_eq, delta)[0] == pytest.approx(10 * 6 / abs(2 * 10 - 10))
    theta = crossover_indices(h, delta, L)
    assert theta[0] == pytest.approx((10 - 10 / 2) / L[0])
    assert theta[1] == pytest.approx((40 - 20 / 2) / L[1])


def test_algorithm2_finds_the_two_modes_of_a_bimodal_histogram() -> None:
    x = np.arange(256)
    rng = np.random.default_rng(0)
    hist = 3000 * np.exp(-0.5 * ((x - 180) / 12) ** 2) + 600 * np.exp(-0.5 * ((x - 60) / 10) ** 2)
    hist += rng.uniform(0, 20, 256)
    peaks = dominant_peaks(hist).dominant
    assert any(abs(p - 180) <= 4 for p in peaks)
    assert any(abs(p - 60) <= 4 for p in peaks)


def test_flat_histogram_still_has_one_dominant_peak() -> None:
    assert len(dominant_peaks(np.ones(256)).dominant) == 1


def test_eq16_valley_emphasis_threshold_falls_in_the_valley() -> None:
    x = np.arange(256)
    hist = 5000 * np.exp(-0.5 * ((x - 190) / 10) ** 2) + 300 * np.exp(-0.5 * ((x - 70) / 8) ** 2)
    t = valley_emphasis_threshold(hist)
    assert 85 < t < 170
    with pytest.raises(ValueError):
        valley_emphasis_threshold(np.zeros(256))
