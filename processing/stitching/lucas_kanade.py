"""Sub-pixel Euclidean refinement by inverse-compositional Lucas–Kanade (Baker & Matthews 2004).

The per-point sampling and update loop is compiled (numba, ``nogil``) so that frame pairs
are refined on several threads at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from processing.stitching.phase import Gray


def _strong_points(
    mag: NDArray[np.float32], n: int, cells: int = 6
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """About ``n`` pixels (x, y) of strong gradient, spread over a ``cells`` x ``cells`` grid:
    in each cell, the strongest of every other pixel (neighbours carry the same information)."""
    sub = mag[::2, ::2]
    h, w = sub.shape
    ch, cw = h // cells, w // cells
    per = int(min(max(1, n // (cells * cells)), ch * cw))
    blocks = (
        sub[: ch * cells, : cw * cells]
        .reshape(cells, ch, cells, cw)
        .transpose(0, 2, 1, 3)
        .reshape(cells * cells, ch * cw)
    )
    thr = np.partition(blocks, ch * cw - per, axis=1)[:, ch * cw - per]
    full_thr = np.repeat(np.repeat(thr.reshape(cells, cells), ch, axis=0), cw, axis=1)
    ys, xs = np.nonzero(sub[: ch * cells, : cw * cells] >= full_thr)
    return 2 * xs, 2 * ys


@dataclass(frozen=True)
class Smoothed:
    """A grey image smoothed for registration (one pyramid level); gradients on demand."""

    image: Gray

    @classmethod
    def of(cls, gray: Gray, sigma: float) -> Smoothed:
        """Smooth by a Gaussian of ``sigma``."""
        # truncated at 2σ: cheaper, as good for registration
        return cls(cast(Gray, cv2.GaussianBlur(gray, (5, 5), sigma)))

    def crop(self, x0: int, y0: int, x1: int, y1: int) -> Smoothed:
        """A rectangle of it."""
        return Smoothed(self.image[y0:y1, x0:x1])


def refine_euclidean(
    template: Smoothed,
    image: Gray,
    W0: NDArray[np.float64],
    *,
    points: int = 4000,
    iterations: int = 30,
) -> tuple[NDArray[np.float64], float, float, float]:
    """Sub-pixel Euclidean warp (2x3, template pixel → image pixel) by inverse-compositional
    Lucas–Kanade (Baker & Matthews 2004) on the template's strongest-gradient pixels, with a
    gain and offset between the two images estimated at every step (exposure changes).
    Both images are smoothed alike beforehand (:class:`Smoothed`). Returns the warp, the
    correlation coefficient of the matched pixels and their mean grey level in the template
    and in the image."""
    gx = cv2.Sobel(template.image, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(template.image, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    mag = cast(NDArray[np.float32], cv2.magnitude(gx, gy))
    mag[:2], mag[-2:], mag[:, :2], mag[:, -2:] = 0, 0, 0, 0
    xs, ys = _strong_points(mag, points)
    h, w = mag.shape
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    X, Y = xs - c[0], ys - c[1]
    Gx, Gy = gx[ys, xs].astype(np.float64), gy[ys, xs].astype(np.float64)
    # steepest-descent images (θ about the centre, tx, ty)
    SD = np.column_stack([Gx * -Y + Gy * X, Gx, Gy])
    H_inv = np.linalg.inv(SD.T @ SD)
    Tv = template.image[ys, xs].astype(np.float64)
    Tc = Tv - Tv.mean()
    t_var = float(Tc @ Tc)
    W = np.vstack([W0, [0, 0, 1]]).astype(np.float64)
    Iw = np.empty(len(xs))
    _lk_iterate(
        np.asarray(image, dtype=np.float32),
        xs.astype(np.float64),
        ys.astype(np.float64),
        SD,
        H_inv,
        Tc,
        t_var,
        float(c[0]),
        float(c[1]),
        float(max(w, h)),
        W,
        Iw,
        iterations,
    )
    Ic = Iw - Iw.mean()
    score = float(Ic @ Tc) / max(float(np.sqrt((Ic @ Ic) * t_var)), 1e-12)
    return W[:2], score, float(Tv.mean()), float(Iw.mean())


@numba.njit(nogil=True, cache=True, inline="always")
def _cubic(t: float) -> tuple[float, float, float, float]:  # pragma: no cover - compiled
    """Keys' cubic convolution weights (a = -0.5) of the samples at -1, 0, 1, 2 for offset t."""
    t2 = t * t
    t3 = t2 * t
    return (
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    )


@numba.njit(nogil=True, cache=True, inline="always")
def _sample(
    image: Gray, qx: float, qy: float, rows: int, cols: int
) -> float:  # pragma: no cover - compiled
    """The image at (qx, qy) by bicubic interpolation, edges replicated."""
    qx = min(max(qx, 0.0), cols - 1.0)
    qy = min(max(qy, 0.0), rows - 1.0)
    x0, y0 = int(qx), int(qy)
    wx = _cubic(qx - x0)
    wy = _cubic(qy - y0)
    out = 0.0
    for a in range(4):
        y = min(max(y0 - 1 + a, 0), rows - 1)
        row = 0.0
        for b in range(4):
            row += wx[b] * image[y, min(max(x0 - 1 + b, 0), cols - 1)]
        out += wy[a] * row
    return out


@numba.njit(nogil=True, cache=True)
def _lk_iterate(
    image: Gray,
    xs: NDArray[np.float64],
    ys: NDArray[np.float64],
    SD: NDArray[np.float64],
    H_inv: NDArray[np.float64],
    Tc: NDArray[np.float64],
    t_var: float,
    cx: float,
    cy: float,
    extent: float,
    W: NDArray[np.float64],
    Iw: NDArray[np.float64],
    iterations: int,
) -> None:  # pragma: no cover - compiled
    """The Lucas–Kanade iterations of :func:`refine_euclidean`, compiled: sample the image
    at the warped points (bilinear, edges replicated), estimate the gain, step, update
    ``W`` in place (W ← W ∘ D⁻¹); ``Iw`` ends as the last samples."""
    rows, cols = image.shape
    n = len(xs)
    for p in range(n):  # the template's own values stand in until the first sample
        Iw[p] = Tc[p]
    for _ in range(iterations):
        total = 0.0
        for p in range(n):
            qx = W[0, 0] * xs[p] + W[0, 1] * ys[p] + W[0, 2]
            qy = W[1, 0] * xs[p] + W[1, 1] * ys[p] + W[1, 2]
            Iw[p] = _sample(image, qx, qy, rows, cols)
            total += Iw[p]
        mean = total / n
        dot = 0.0
        for p in range(n):
            dot += (Iw[p] - mean) * Tc[p]
        alpha = dot / t_var
        if abs(alpha) < 1e-6:
            break
        b0 = b1 = b2 = 0.0
        for p in range(n):
            e = (Iw[p] - mean) / alpha - Tc[p]
            b0 += SD[p, 0] * e
            b1 += SD[p, 1] * e
            b2 += SD[p, 2] * e
        d0 = H_inv[0, 0] * b0 + H_inv[0, 1] * b1 + H_inv[0, 2] * b2
        d1 = H_inv[1, 0] * b0 + H_inv[1, 1] * b1 + H_inv[1, 2] * b2
        d2 = H_inv[2, 0] * b0 + H_inv[2, 1] * b1 + H_inv[2, 2] * b2
        ct, st = np.cos(d0), np.sin(d0)
        # W <- W o D^-1, D = rotation d0 about the centre then translation (d1, d2)
        r00, r01, r10, r11 = ct, st, -st, ct
        tx = cx - (r00 * (cx + d1) + r01 * (cy + d2))
        ty = cy - (r10 * (cx + d1) + r11 * (cy + d2))
        a00 = W[0, 0] * r00 + W[0, 1] * r10
        a01 = W[0, 0] * r01 + W[0, 1] * r11
        a02 = W[0, 0] * tx + W[0, 1] * ty + W[0, 2]
        a10 = W[1, 0] * r00 + W[1, 1] * r10
        a11 = W[1, 0] * r01 + W[1, 1] * r11
        a12 = W[1, 0] * tx + W[1, 1] * ty + W[1, 2]
        W[0, 0], W[0, 1], W[0, 2] = a00, a01, a02
        W[1, 0], W[1, 1], W[1, 2] = a10, a11, a12
        if abs(d0) * extent + abs(d1) + abs(d2) < 2e-3:
            break
