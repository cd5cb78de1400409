"""Multi-scale Hessian line emphasis of Sato et al. and Fujita et al. (paper eqs. 10-14)."""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
from numpy.typing import NDArray


def hessian_eigenvalues(image: NDArray[np.floating], sigma: float) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Eigenvalues λ1 ≥ λ2 of the Gaussian-smoothed Hessian (eqs. 10, 11, 13), each (M, N)."""
    if sigma <= 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    img = np.asarray(image, dtype=np.float32)
    ksize = int(2 * round(3 * sigma) + 1)
    smooth = cv2.GaussianBlur(img, (ksize, ksize), sigma, borderType=cv2.BORDER_REFLECT)
    ixx = cv2.Sobel(smooth, cv2.CV_32F, 2, 0, ksize=3) / 4.0
    iyy = cv2.Sobel(smooth, cv2.CV_32F, 0, 2, ksize=3) / 4.0
    ixy = cv2.Sobel(smooth, cv2.CV_32F, 1, 1, ksize=3) / 4.0
    half_trace = (ixx + iyy) / 2
    root = np.sqrt(((ixx - iyy) / 2) ** 2 + ixy**2)
    return half_trace + root, half_trace - root


def line_measure(l1: NDArray[np.floating], l2: NDArray[np.floating], mu: float) -> NDArray[np.float32]:
    """Similarity to a bright line λ12 of eq. (12) from eigenvalues λ1 ≥ λ2, 0 < μ ≤ 1."""
    if not 0 < mu <= 1:
        raise ValueError(f"mu must be in (0, 1], got {mu}")
    # |λ2| + λ1 when λ1 ≤ 0, |λ2| - μλ1 when 0 < λ1 < |λ2|/μ (positive exactly then), else 0
    a2 = np.abs(l2)
    out = a2 + np.minimum(l1, 0) - mu * np.maximum(l1, 0)
    np.maximum(out, 0, out=out)
    out *= l2 < 0
    return out.astype(np.float32, copy=False)


def line_emphasis(
    image: NDArray[np.floating],
    *,
    sigma1: float = 1.0,
    scale_factor: float = 2 ** 0.5,
    n_scales: int = 4,
    mu: float = 0.5,
    dark_lines: bool = True,
    normalise: bool = False,
    half_resolution_from: float | None = None,
) -> NDArray[np.float32]:
    """Multi-scale line filter R(x) = max_i σ_1² λ12(x; σ_i), σ_i = s^(i-1) σ_1 (eq. 14).

    Parameters
    ----------
    image : (M, N) array.
    dark_lines : emphasise dark lines (cracks) by filtering the negated image.
    normalise : use σ_i² instead of the published σ_1² factor (scale-normalised response,
        so wide cracks are not suppressed; the ``proposed`` method's choice).
    half_resolution_from : compute scales σ ≥ this on the image halved (σ/2 there, the
        eigenvalues rescaled), then upsample: about 4x less work for the coarse scales.
    """
    if n_scales < 1 or sigma1 <= 0 or scale_factor <= 0:
        raise ValueError("n_scales must be >= 1 and sigma1, scale_factor positive")
    img = np.asarray(image, dtype=np.float32)
    if dark_lines:
        img = -img

    half = None
    if half_resolution_from is not None and min(img.shape) >= 32:
        half = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)

    def at_scale(sigma: float) -> NDArray[np.float32]:
        weight = sigma**2 if normalise else sigma1**2
        if half is not None and half_resolution_from is not None and sigma >= half_resolution_from:
            l1, l2 = hessian_eigenvalues(half, sigma / 2)  # derivatives per half-res pixel: 4x
            r = weight * line_measure(l1 / 4, l2 / 4, mu)
            return cv2.resize(r, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR)
        l1, l2 = hessian_eigenvalues(img, sigma)
        return weight * line_measure(l1, l2, mu)

    scales = sigmas(sigma1, scale_factor, n_scales)
    # OpenCV and NumPy release the GIL: the scales run on both cores
    with ThreadPoolExecutor(max_workers=min(len(scales), 2)) as pool:
        responses = list(pool.map(at_scale, scales))
    return np.maximum.reduce(responses)


def sigmas(sigma1: float, scale_factor: float, n_scales: int) -> Sequence[float]:
    """The discrete scales σ_i = s^(i-1) σ_1, i = 1..n."""
    return [sigma1 * scale_factor**i for i in range(n_scales)]
