"""Exposure: per-frame gains that make overlapping frames equally bright."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import spsolve

from processing.stitching.registration import PairMeasurement


def solve_gains(
    n: int, measurements: Sequence[PairMeasurement], *, sigma_n: float = 0.5, sigma_g: float = 0.1
) -> NDArray[np.float64]:
    """Per-frame exposure gains that make overlapping frames equally bright (Brown & Lowe's
    gain compensation: min Σ (g_i m_i − g_j m_j)² / σ_n² + Σ (g_k − 1)² / σ_g², with m the
    mean grey of the same surface points in both frames; Brown & Lowe sum the first term
    over every overlapping pixel, here one term per pair carries that weight by a small
    σ_n, so the prior only fixes the overall level)."""
    A = sp.lil_matrix((n, n))
    b = np.full(n, 1.0 / sigma_g**2)
    for k in range(n):
        A[k, k] = 1.0 / sigma_g**2
    for m in measurements:
        a, c = m.mean_i, m.mean_j
        A[m.i, m.i] += a * a / sigma_n**2
        A[m.j, m.j] += c * c / sigma_n**2
        A[m.i, m.j] -= a * c / sigma_n**2
        A[m.j, m.i] -= a * c / sigma_n**2
    return np.asarray(spsolve(A.tocsc(), b), dtype=np.float64)
