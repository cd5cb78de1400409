import cv2
import numpy as np
import pytest

from processing.detection.ridges import (
    hessian_eigenvalues,
    line_emphasis,
    line_measure,
    line_response,
)


def test_eq12_line_measure_cases() -> None:
    l1 = np.array([-1.0, 1.0, 9.0, 1.0])
    l2 = np.array([-4.0, -4.0, -4.0, 2.0])
    out = line_measure(l1, l2, mu=0.5)
    assert out[0] == pytest.approx(4 + -1)  # λ2 ≤ λ1 ≤ 0: |λ2| + λ1
    assert out[1] == pytest.approx(4 - 0.5 * 1)  # λ2 < 0 < λ1 < |λ2|/μ
    assert out[2] == 0 and out[3] == 0  # otherwise
    with pytest.raises(ValueError, match="mu"):
        line_measure(l1, l2, mu=0)


def test_dark_line_responds_and_blob_and_flat_do_not() -> None:
    img = np.full((80, 80), 200, np.float32)
    cv2.line(img, (5, 20), (75, 20), 60, 3)
    cv2.circle(img, (40, 60), 6, 60, -1)
    R = line_emphasis(img, sigma1=1.0, n_scales=3)
    assert R[20, 40] > 5 * R[60, 40]  # line centre vs blob centre
    assert R[40, 10] == pytest.approx(0, abs=1e-3)  # flat surface
    assert line_emphasis(np.full((20, 20), 7.0)).max() == pytest.approx(0, abs=1e-4)


def test_hessian_eigenvalues_are_ordered() -> None:
    rng = np.random.default_rng(0)
    l1, l2 = hessian_eigenvalues(rng.normal(size=(32, 32)).astype(np.float32), 1.5)
    assert (l1 >= l2).all()


@pytest.mark.parametrize("mu", [0.25, 0.5, 1.0])
def test_fused_line_response_equals_eq12_from_eigenvalues(mu: float) -> None:
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.normal(size=(64, 64)).astype(np.float32), (5, 5), 1.0)
    l1, l2 = hessian_eigenvalues(img, 1.4)
    expected = 2.0 * line_measure(l1, l2, mu)
    assert np.allclose(line_response(img, 1.4, mu, weight=2.0), expected, atol=1e-6)
