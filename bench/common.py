"""What every benchmark shares: the result type and small geometric helpers."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

Result = dict[str, Any]


def rigid_align_2d(src: NDArray[np.float64], dst: NDArray[np.float64]) -> NDArray[np.float64]:
    """``src`` points moved by the rotation and translation that best fit them to ``dst``."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((dst - md).T @ (src - ms))
    R = U @ np.diag([1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return (src - ms) @ R.T + md


def similarity_align_2d(src: NDArray[np.float64], dst: NDArray[np.float64]) -> NDArray[np.float64]:
    """``src`` points moved by the rotation, uniform scale and translation that best fit them
    to ``dst`` (Umeyama 1991)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    scale = float(np.trace(np.diag(S) @ D)) / max(float((a**2).sum() / len(src)), 1e-12)
    return scale * a @ R.T + md
