"""Automatic histogram peak detection and valley-emphasis Otsu (paper §3.3.1, eqs. 3-9, 16-17).

The "lost mountain explorer" strategy: smooth the histogram, take its local maxima as a
draft plan, then keep as dominant the peaks whose crossover index stands above both
neighbours, moving the observing location after each one (Algorithm 2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


def smooth_histogram(hist: NDArray[np.floating]) -> NDArray[np.float64]:
    """3-tap moving average h(i) = [h(i-1) + h(i) + h(i+1)] / 3 (eq. 3), edges replicated."""
    h = np.asarray(hist, dtype=np.float64)
    if h.ndim != 1 or h.size < 3:
        raise ValueError(f"hist must be 1-D with at least 3 bins, got shape {h.shape}")
    padded = np.pad(h, 1, mode="edge")
    return (padded[:-2] + padded[1:-1] + padded[2:]) / 3.0


def initial_peaks(h: NDArray[np.floating]) -> NDArray[np.intp]:
    """Indices δ with h(δ) > h(δ-1) and h(δ) > h(δ+1) (eq. 4); plateaus count once (left edge)."""
    h = np.asarray(h, dtype=np.float64)
    left = np.concatenate([[-np.inf], h[:-1]])
    # compare with the next *different* value so a flat-topped peak is still found
    right = h.copy()
    nxt = -np.inf
    for i in range(len(h) - 1, -1, -1):
        right[i] = nxt
        if i > 0 and h[i] != h[i - 1]:
            nxt = h[i]
    return np.nonzero((h > left) & (h > right))[0]


def offset_distances(h: NDArray[np.floating], delta: NDArray[np.intp]) -> NDArray[np.float64]:
    """Offset distance L(δ(k)) from each peak to its observing location (eq. 6).

    L = h(δk)·[g(δk+1) - g(δk)] / |h(δk+1) - h(δk)|, or with (k+1)/k·h(δk+1) in the
    denominator when the two heights are equal. The last peak uses its left neighbour.
    """
    h = np.asarray(h, dtype=np.float64)
    n = len(delta)
    out = np.zeros(n)
    for k in range(n):
        j = k + 1 if k + 1 < n else k - 1
        if j < 0:
            out[k] = float(delta[k]) or 1.0
            continue
        gap = abs(float(delta[j] - delta[k]))
        hk, hj = h[delta[k]], h[delta[j]]
        if hj != hk:
            den = abs(hj - hk)
        else:
            kk = k + 1  # the paper counts peaks from 1
            den = abs((kk + 1) / kk * hj - hk)
        out[k] = hk * gap / den if den > 0 else np.inf
    return out


def crossover_indices(h: NDArray[np.floating], delta: NDArray[np.intp], L: NDArray[np.float64]) -> NDArray[np.float64]:
    """Crossover index θ(δk) = d(δk) / L(δk), d = h(δk) - min(h(δk), h(δk+1)) / 2 (eq. 8)."""
    h = np.asarray(h, dtype=np.float64)
    n = len(delta)
    theta = np.zeros(n)
    for k in range(n):
        j = k + 1 if k + 1 < n else max(k - 1, 0)
        d = h[delta[k]] - min(h[delta[k]], h[delta[j]]) / 2.0
        theta[k] = d / L[k] if np.isfinite(L[k]) and L[k] > 0 else 0.0
    return theta


@dataclass(frozen=True)
class PeakResult:
    """Dominant peaks (grey levels), their observing locations and the draft plan."""

    dominant: NDArray[np.intp]
    observing: NDArray[np.float64]
    initial: NDArray[np.intp]


def dominant_peaks(hist: NDArray[np.floating]) -> PeakResult:
    """Algorithm 2: dominant peaks of a histogram by the crossover-index search (eqs. 3-9).

    A peak j is dominant when θ(δj) > θ(δj-1) and θ(δj) > θ(δj+1) (eq. 9); after each
    one the observing location moves to g(δj) - L(δj) (eq. 7), its index is reset and the
    search goes on from the next peak. If the search finds none, the highest peak is
    the single dominant one.
    """
    h = smooth_histogram(hist)
    delta = initial_peaks(h)
    if len(delta) == 0:
        return PeakResult(np.array([int(np.argmax(h))]), np.array([0.0]), delta)
    L = offset_distances(h, delta)
    theta = crossover_indices(h, delta, L)
    theta_ext = np.concatenate([[0.0], theta, [0.0]])  # virtual neighbours at both ends
    beta: list[int] = []
    alpha: list[float] = [float(delta[0] - L[0])]
    n = 0
    for k in range(n, len(delta) + 1):
        for j in range(n, k):
            jj = j + 1  # index into theta_ext
            if theta_ext[jj] > theta_ext[jj - 1] and theta_ext[jj] > theta_ext[jj + 1]:
                beta.append(int(delta[j]))
                alpha.append(float(delta[j] - L[j]))
                theta_ext[jj] = 0.0  # reset after it is taken
                n = j + 1
                break
    if not beta:
        beta = [int(delta[np.argmax(h[delta])])]
    return PeakResult(np.array(sorted(set(beta))), np.array(alpha), delta)


def valley_emphasis_threshold(hist: NDArray[np.floating]) -> int:
    """Valley-emphasis Otsu: t* = argmax (1 - p_t)(ω1 μ1² + ω2 μ2²) (eqs. 16-17)."""
    h = np.asarray(hist, dtype=np.float64)
    total = h.sum()
    if total <= 0:
        raise ValueError("hist must not be empty")
    p = h / total
    levels = np.arange(len(p), dtype=np.float64)
    w1 = np.cumsum(p)
    w2 = 1.0 - w1
    m1 = np.cumsum(p * levels)
    mt = m1[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        mu1 = np.where(w1 > 0, m1 / w1, 0.0)
        mu2 = np.where(w2 > 1e-12, (mt - m1) / w2, 0.0)
    score = (1.0 - p) * (w1 * mu1**2 + w2 * mu2**2)
    score[w2 <= 1e-12] = -np.inf
    score[w1 <= 0] = -np.inf
    if not np.isfinite(score).any():
        return int(np.argmax(h))
    return int(np.argmax(score))
