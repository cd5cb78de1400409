"""Multi-scale Hessian line emphasis of Sato et al. and Fujita et al. (paper eqs. (10)–(14))."""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]


def _hessian(
    image: NDArray[np.float32], sigma: float
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """Half trace (Ixx + Iyy)/2, half difference (Ixx − Iyy)/2 and Ixy of the
    Gaussian-smoothed image (eqs. (10), 11), each (M, N) float32."""
    if sigma <= 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    ksize = int(2 * round(3 * sigma) + 1)
    smooth = cv2.GaussianBlur(image, (ksize, ksize), sigma, borderType=cv2.BORDER_REFLECT)
    # 3x3 Sobel second derivatives carry a [1 2 1] smoothing that sums to 4
    ixx = cv2.Sobel(smooth, cv2.CV_32F, 2, 0, ksize=3, scale=0.125)
    iyy = cv2.Sobel(smooth, cv2.CV_32F, 0, 2, ksize=3, scale=0.125)
    ixy = cv2.Sobel(smooth, cv2.CV_32F, 1, 1, ksize=3, scale=0.25)
    return cast(F32, cv2.add(ixx, iyy)), cast(F32, cv2.subtract(ixx, iyy)), cast(F32, ixy)


def hessian_eigenvalues(
    image: NDArray[np.floating], sigma: float
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Eigenvalues λ1 ≥ λ2 of the Gaussian-smoothed Hessian (eqs. (10), 11, 13), each (M, N)."""
    half_trace, half_diff, ixy = _hessian(np.asarray(image, dtype=np.float32), sigma)
    root = cv2.magnitude(half_diff, ixy)
    return cast(F32, cv2.add(half_trace, root)), cast(F32, cv2.subtract(half_trace, root))


def line_measure(
    l1: NDArray[np.floating], l2: NDArray[np.floating], mu: float
) -> NDArray[np.float32]:
    """Similarity to a bright line λ12 of eq. (12) from eigenvalues λ1 ≥ λ2, 0 < μ ≤ 1."""
    if not 0 < mu <= 1:
        raise ValueError(f"mu must be in (0, 1], got {mu}")
    # |λ2| + λ1 when λ1 ≤ 0, |λ2| - μλ1 when 0 < λ1 < |λ2|/μ (positive exactly then), else 0
    a2 = np.abs(l2)
    out = a2 + np.minimum(l1, 0) - mu * np.maximum(l1, 0)
    np.maximum(out, 0, out=out)
    out *= l2 < 0
    return out.astype(np.float32, copy=False)


def line_response(
    image: NDArray[np.float32], sigma: float, mu: float, weight: float = 1.0
) -> NDArray[np.float32]:
    """``weight`` · λ12(x; σ) of eq. (12), computed from the Hessian without forming λ1, λ2
    (see :func:`_max_line_response`)."""
    out = np.zeros(image.shape, np.float32)
    _accumulate_line_response(np.asarray(image, dtype=np.float32), sigma, mu, weight, out)
    return out


def _accumulate_line_response(
    image: NDArray[np.float32], sigma: float, mu: float, weight: float, out: NDArray[np.float32]
) -> None:
    """``out`` ← max(``out``, ``weight`` · λ12(x; σ)): Gaussian smoothing, then one fused pass."""
    if sigma <= 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    if not 0 < mu <= 1:
        raise ValueError(f"mu must be in (0, 1], got {mu}")
    ksize = int(2 * round(3 * sigma) + 1)
    smooth = cv2.GaussianBlur(image, (ksize, ksize), sigma, borderType=cv2.BORDER_REFLECT)
    padded = cv2.copyMakeBorder(smooth, 1, 1, 1, 1, cv2.BORDER_REFLECT_101)  # as cv2.Sobel's border
    _max_line_response(cast(F32, padded), out, np.float32(weight), np.float32(mu))


@numba.njit(nogil=True, cache=True)
def _max_line_response(
    p: NDArray[np.float32], out: NDArray[np.float32], weight: np.float32, mu: np.float32
) -> None:  # pragma: no cover - compiled
    """One pass over a padded smoothed image: the 3x3 Sobel Hessian (as :func:`_hessian`)
    and eq. (12) in closed form, max-accumulated into ``out``.

    With h = (Ixx + Iyy)/2 and r = ((Ixx − Iyy)²/4 + Ixy²)^½ (so λ1,2 = h ± r), eq. (12)
    is 2r where λ1 ≤ 0 and max(0, (1 − μ) r − (1 + μ) h) where λ1 > 0, which is
    clip((1 − μ) r − (1 + μ) h, 0, 2r) everywhere (``out`` starts at 0 or above).
    """
    rows, cols = out.shape
    a = weight * (1 - mu)
    b = -weight * (1 + mu)
    c = 2 * weight
    for y in range(rows):
        for x in range(cols):
            p00, p01, p02 = p[y, x], p[y, x + 1], p[y, x + 2]
            p10, p11, p12 = p[y + 1, x], p[y + 1, x + 1], p[y + 1, x + 2]
            p20, p21, p22 = p[y + 2, x], p[y + 2, x + 1], p[y + 2, x + 2]
            hxx = (
                (p00 - 2 * p01 + p02) + 2 * (p10 - 2 * p11 + p12) + (p20 - 2 * p21 + p22)
            ) * 0.125
            hyy = (
                (p00 - 2 * p10 + p20) + 2 * (p01 - 2 * p11 + p21) + (p02 - 2 * p12 + p22)
            ) * 0.125
            ixy = (p22 - p20 - p02 + p00) * 0.25
            r = np.sqrt((hxx - hyy) * (hxx - hyy) + ixy * ixy)
            v = min(a * r + b * (hxx + hyy), c * r)
            if v > out[y, x]:
                out[y, x] = v


def line_emphasis(
    image: NDArray[np.integer | np.floating],
    *,
    sigma1: float = 1.0,
    scale_factor: float = 2**0.5,
    n_scales: int = 4,
    mu: float = 0.5,
    dark_lines: bool = True,
    normalise: bool = False,
    half_resolution_from: float | None = None,
) -> NDArray[np.float32]:
    """Multi-scale line filter R(x) = max_i σ_1² λ12(x; σ_i), σ_i = s^(i-1) σ_1 (eq. (14)).

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
        img = cv2.multiply(img, -1.0)  # type: ignore[call-overload]  # OpenCV's stubs lack the scalar form
    h, w = img.shape
    half = None
    if half_resolution_from is not None and min(img.shape) >= 32:
        half = cast(F32, cv2.resize(img, (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    out = np.zeros((h, w), np.float32)
    coarse = np.zeros(half.shape, np.float32) if half is not None else None
    for sigma in sigmas(sigma1, scale_factor, n_scales):
        weight = sigma**2 if normalise else sigma1**2
        if (
            half is not None
            and coarse is not None
            and half_resolution_from is not None
            and sigma >= half_resolution_from
        ):
            # derivatives per half-resolution pixel are 4x those per pixel
            _accumulate_line_response(half, sigma / 2, mu, weight / 4, coarse)
        else:
            _accumulate_line_response(img, sigma, mu, weight, out)
    if coarse is not None and coarse.any():
        cv2.max(out, cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR), dst=out)
    return out


def sigmas(sigma1: float, scale_factor: float, n_scales: int) -> Sequence[float]:
    """The discrete scales σ_i = s^(i-1) σ_1, i = 1..n."""
    return [sigma1 * scale_factor**i for i in range(n_scales)]
