"""Automatic histogram peak detection and valley-emphasis Otsu (paper §3.3.1, eqs. (3)–(9), 16-17).

The "lost mountain explorer" strategy: smooth the histogram, take its local maxima as a
draft plan, then keep as dominant the peaks whose crossover index stands above both
neighbours, moving the observing location after each one (Algorithm 2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


def smooth_histogram(hist: NDArray[np.floating]) -> NDArray[np.float64]:
    """3-tap moving average h(i) = [h(i-1) + h(i) + h(i+1)] / 3 (eq. (3)), edges replicated."""
    h = np.asarray(hist, dtype=np.float64)
    if h.ndim != 1 or h.size < 3:
        raise ValueError(f"hist must be 1-D with at least 3 bins, got shape {h.shape}")
    padded = np.pad(h, 1, mode="edge")
    return (padded[:-2] + padded[1:-1] + padded[2:]) / 3.0


def initial_peaks(h: NDArray[np.floating]) -> NDArray[np.intp]:
    """Indices δ with h(δ) > h(δ-1) and h(δ) > h(δ+1) (eq. (4)); plateaus count once (left edge)."""
    h = np.asarray(h, dtype=np.float64)
    n = len(h)
    # for each bin, the next bin whose value differs (so a flat-topped peak is still found)
    change = np.nonzero(np.diff(h) != 0)[0] + 1  # first index of each new run
    run_start = np.zeros(n, np.intp)
    run_start[change] = change
    run_start = np.maximum.accumulate(run_start)
    nxt_idx = np.searchsorted(change, run_start, side="right")
    right = np.full(n, -np.inf)
    has_next = nxt_idx < len(change)
    right[has_next] = h[change[nxt_idx[has_next]]]
    left = np.concatenate([[-np.inf], h[:-1]])
    return np.nonzero((h > left) & (h > right))[0]


def _neighbours(n: int) -> NDArray[np.intp]:
    """Index of the peak each one is compared with: the next, the previous for the last."""
    j = np.arange(1, n + 1)
    if n:
        j[-1] = max(n - 2, 0)
    return j


def offset_distances(h: NDArray[np.floating], delta: NDArray[np.intp]) -> NDArray[np.float64]:
    """Offset distance L(δ(k)) from each peak to its observing location (eq. (6)).

    L = h(δk)·[g(δk+1) - g(δk)] / |h(δk+1) - h(δk)|, or with (k+1)/k·h(δk+1) in the
    denominator when the two heights are equal. The last peak uses its left neighbour.
    """
    h = np.asarray(h, dtype=np.float64)
    n = len(delta)
    if n == 1:
        return np.array([float(delta[0]) or 1.0])
    j = _neighbours(n)
    hk, hj = h[delta], h[delta[j]]
    gap = np.abs(delta[j] - delta).astype(np.float64)
    k1 = np.arange(1, n + 1, dtype=np.float64)  # the paper counts peaks from 1
    den = np.where(hj != hk, np.abs(hj - hk), np.abs((k1 + 1) / k1 * hj - hk))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, hk * gap / den, np.inf)


def crossover_indices(
    h: NDArray[np.floating], delta: NDArray[np.intp], L: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Crossover index θ(δk) = d(δk) / L(δk), d = h(δk) - min(h(δk), h(δk+1)) / 2 (eq. (8))."""
    h = np.asarray(h, dtype=np.float64)
    n = len(delta)
    j = _neighbours(n) if n > 1 else np.zeros(1, np.intp)
    d = h[delta] - np.minimum(h[delta], h[delta[j]]) / 2.0
    ok = np.isfinite(L) & (L > 0)
    return np.where(ok, d / np.where(ok, L, 1.0), 0.0)


@dataclass(frozen=True)
class PeakResult:
    """Dominant peaks (grey levels), their observing locations and the draft plan."""

    dominant: NDArray[np.intp]
    observing: NDArray[np.float64]
    initial: NDArray[np.intp]


def dominant_peaks(hist: NDArray[np.floating]) -> PeakResult:
    """Algorithm 2: dominant peaks of a histogram by the crossover-index search (eqs. (3)–(9)).

    A peak j is dominant when θ(δj) > θ(δj-1) and θ(δj) > θ(δj+1) (eq. (9)); after each
    one the observing location moves to g(δj) - L(δj) (eq. (7)), its index is reset and the
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
    """Valley-emphasis Otsu: t* = argmax (1 - p_t)(ω1 μ1² + ω2 μ2²) (eqs. (16)–(17))."""
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
