"""Euclidean warps (2x3, template pixel -> image pixel) carried between a crop and the
whole image, a moved template origin and pyramid levels."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from processing.stitching.phase import Gray


def crop_for(
    image: Gray, W: NDArray[np.float64], tw: int, th: int, pad: int
) -> tuple[Gray, NDArray[np.float64]]:
    """The part of ``image`` that a (tw x th) template reaches through warp ``W`` (plus
    ``pad``), and the warp into that part."""
    corners = W[:2] @ np.array([[0, 0, 1], [tw, 0, 1], [0, th, 1], [tw, th, 1]], float).T
    x0, y0 = (max(0, int(np.floor(v)) - pad) for v in corners.min(axis=1))
    x1, y1 = (int(np.ceil(v)) + pad for v in corners.max(axis=1))
    out = W[:2].copy()
    out[:, 2] -= (x0, y0)
    return image[y0 : min(y1, image.shape[0]), x0 : min(x1, image.shape[1])], out


def uncrop(
    W: NDArray[np.float64], crop_W: NDArray[np.float64], crop_W0: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Warp ``W``, found in a crop whose warp ``crop_W`` was ``crop_W0`` in the whole image,
    into the whole image."""
    out = W.copy()
    out[:, 2] += crop_W0[:, 2] - crop_W[:, 2]
    return out


def shift_origin(W: NDArray[np.float64], dx: float, dy: float) -> NDArray[np.float64]:
    """A warp for a template whose pixel (0, 0) sits at (dx, dy) of the original's."""
    return W[:2] @ np.array([[1, 0, dx], [0, 1, dy], [0, 0, 1.0]])


def scale_warp(W: NDArray[np.float64], f: float) -> NDArray[np.float64]:
    """The same Euclidean warp between images scaled by ``f`` (pyramid levels, pixel centres
    at integer coordinates as in ``cv2.pyrDown``)."""
    out = W.copy()
    out[:, 2] = W[:, 2] * f
    return out
