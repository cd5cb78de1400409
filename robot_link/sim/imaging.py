"""Exact image warps for the simulated cameras.

OpenCV's ``warpAffine`` and ``remap`` round every source position to 1/32 pixel (their
interpolation tables). For a rotated frame that rounding is a position error of up to
1/64 px that varies across the frame, which is as large as the errors the stitching
benchmark measures: frames rendered that way are not where their ground truth says to
the precision we score (heading errors of ~7e-5 rad per frame pair came from it alone,
measured). These warps interpolate at the exact position instead.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


def warp_affine_exact(
    texture: NDArray[np.uint8],
    M: NDArray[np.floating],
    size: tuple[int, int],
    border: float | None = None,
) -> NDArray[np.float32]:
    """A (w, h) image whose pixel (x, y) is ``texture`` at M @ (x, y, 1), by bicubic
    convolution (Keys, a = -0.5) at the exact position; beyond the texture's edges it is
    reflected, or reads ``border`` when given (``cv2.BORDER_CONSTANT``); float32, with the
    texture's channels (an (h, w) image for a one-channel texture)."""
    src = texture if texture.ndim == 3 else texture[..., None]
    A = np.asarray(M, dtype=np.float64)
    if A.shape != (2, 3):
        raise ValueError(f"M must be 2x3, got {A.shape}")
    out = np.empty((size[1], size[0], src.shape[2]), np.float32)
    _warp(
        np.ascontiguousarray(src),
        A,
        out,
        border is not None,
        0.0 if border is None else float(border),
    )
    return out if texture.ndim == 3 else out[..., 0]


@numba.njit(cache=True, inline="always")
def _reflect(i: int, n: int) -> int:  # pragma: no cover - compiled
    """Index i reflected into 0..n-1 (``cv2.BORDER_REFLECT``: the edge pixel repeated)."""
    if n == 1:
        return 0
    period = 2 * n
    i %= period
    return i if i < n else period - 1 - i


@numba.njit(cache=True, inline="always")
def _keys(t: float, weights: NDArray[np.float64]) -> None:  # pragma: no cover - compiled
    """Keys' cubic convolution weights (a = -0.5) of the samples at -1, 0, 1, 2 for offset t."""
    t2 = t * t
    t3 = t2 * t
    weights[0] = -0.5 * t3 + t2 - 0.5 * t
    weights[1] = 1.5 * t3 - 2.5 * t2 + 1.0
    weights[2] = -1.5 * t3 + 2.0 * t2 + 0.5 * t
    weights[3] = 0.5 * t3 - 0.5 * t2


@numba.njit(nogil=True, cache=True, fastmath=True)
def _warp(
    src: NDArray[np.uint8],
    M: NDArray[np.float64],
    out: NDArray[np.float32],
    constant: bool,
    value: float,
) -> None:  # pragma: no cover - compiled
    rows, cols, channels = src.shape
    h, w, _ = out.shape
    wx = np.empty(4)
    wy = np.empty(4)
    ix = np.empty(4, np.int64)
    iy = np.empty(4, np.int64)
    for y in range(h):
        for x in range(w):
            qx = M[0, 0] * x + M[0, 1] * y + M[0, 2]
            qy = M[1, 0] * x + M[1, 1] * y + M[1, 2]
            x0, y0 = int(np.floor(qx)), int(np.floor(qy))
            _keys(qx - x0, wx)
            _keys(qy - y0, wy)
            if 1 <= x0 < cols - 2 and 1 <= y0 < rows - 2:
                for c in range(channels):
                    acc = 0.0
                    for a in range(4):
                        r = y0 - 1 + a
                        acc += wy[a] * (
                            wx[0] * src[r, x0 - 1, c]
                            + wx[1] * src[r, x0, c]
                            + wx[2] * src[r, x0 + 1, c]
                            + wx[3] * src[r, x0 + 2, c]
                        )
                    out[y, x, c] = acc
                continue
            for k in range(4):  # near or beyond an edge: reflected taps, or -1 for the constant
                ix[k] = (
                    _reflect(x0 - 1 + k, cols)
                    if not constant
                    else (x0 - 1 + k if 0 <= x0 - 1 + k < cols else -1)
                )
                iy[k] = (
                    _reflect(y0 - 1 + k, rows)
                    if not constant
                    else (y0 - 1 + k if 0 <= y0 - 1 + k < rows else -1)
                )
            for c in range(channels):
                acc = 0.0
                for a in range(4):
                    for b in range(4):
                        tap = value if iy[a] < 0 or ix[b] < 0 else src[iy[a], ix[b], c]
                        acc += wy[a] * wx[b] * tap
                out[y, x, c] = acc
