"""Aligning two visits' images of one surface: a homography from AFTER's pixels to BEFORE's,
robust to a shift, a turn, a scale change, other lighting, new dirt and rust.

Scale-invariant features (SIFT, on contrast-equalised grey) matched with the ratio test
give a first homography by MAGSAC++; the enhanced correlation coefficient (ECC, which is
invariant to a gain and an offset of the grey levels) refines it on the images' gradients
to a fraction of a pixel. Nothing here depends on the images' size or content beyond
"textured enough to match": the feature scale is chosen from the image size.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.metrics import umeyama_alignment


class AlignmentError(ValueError):
    """The two images show no common surface that can be aligned."""


@dataclass(frozen=True)
class AlignParams:
    """How the alignment searches and when it gives up."""

    feature_pixels: int = 1600 * 1600  # features on a copy of at most this many pixels
    ratio: float = 0.8  # Lowe's ratio test (his paper's value)
    min_inliers: int = 15
    ransac_px: float = 3.0  # at the feature copy's scale
    ecc_pixels: int = 1200 * 1200  # refinement on a copy of at most this many pixels
    ecc_iterations: int = 200
    min_overlap: float = 0.2


@dataclass(frozen=True)
class Alignment:
    """AFTER → BEFORE homography (3, 3), its RMS residual over the matched features (px,
    BEFORE's pixels), the fraction of AFTER inside BEFORE, and the inlier count."""

    after_to_before: NDArray[np.float64]
    residual_px: float
    overlap: float
    inliers: int


def _gray(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    g = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8))
    return np.asarray(clahe.apply(np.asarray(g, np.uint8)), np.uint8)


def _scaled(gray: NDArray[np.uint8], pixels: int) -> tuple[NDArray[np.uint8], float]:
    """A copy of at most ``pixels`` pixels (a long strip keeps its short side's detail) and
    its scale."""
    s = min(1.0, float(np.sqrt(pixels / gray.size)))
    if s == 1.0:
        return gray, 1.0
    small = cv2.resize(gray, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    return np.asarray(small, np.uint8), s


def _scale_h(H: NDArray[np.float64], s_after: float, s_before: float) -> NDArray[np.float64]:
    """H between scaled copies → H between the full images."""
    return np.diag([1 / s_before, 1 / s_before, 1.0]) @ H @ np.diag([s_after, s_after, 1.0])


def feature_homography(
    before: NDArray[np.uint8], after: NDArray[np.uint8], params: AlignParams = AlignParams()
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """First AFTER → BEFORE homography from features, and the inlier point pairs (N, 2)
    each, in full-image pixels (``before``, ``after``: equalised grey images)."""
    b, sb = _scaled(before, params.feature_pixels)
    a, sa = _scaled(after, params.feature_pixels)
    sift = cv2.SIFT_create(nfeatures=8000)  # type: ignore[attr-defined]  # the stubs omit SIFT
    kb, db = sift.detectAndCompute(b, None)
    ka, da = sift.detectAndCompute(a, None)
    if db is None or da is None or len(kb) < params.min_inliers or len(ka) < params.min_inliers:
        raise AlignmentError("too little texture to align the two images")
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [
        m for m, n in (p for p in pairs if len(p) == 2) if m.distance < params.ratio * n.distance
    ]
    if len(good) < params.min_inliers:
        raise AlignmentError(f"only {len(good)} features match: the images do not overlap")
    pa = np.array([ka[m.queryIdx].pt for m in good], np.float64)
    pb = np.array([kb[m.trainIdx].pt for m in good], np.float64)
    found, inl = cv2.findHomography(pa, pb, cv2.USAC_MAGSAC, params.ransac_px, maxIters=10000)
    H = None if found is None else np.asarray(found, np.float64)
    if H is None or int(inl.sum()) < params.min_inliers:
        raise AlignmentError("no consistent alignment between the two images")
    keep = inl.ravel().astype(bool)
    return _scale_h(H, sa, sb), pa[keep] / sa, pb[keep] / sb


def refine_ecc(
    before: NDArray[np.uint8],
    after: NDArray[np.uint8],
    H: NDArray[np.float64],
    params: AlignParams = AlignParams(),
) -> NDArray[np.float64] | None:
    """``H`` refined by ECC on the gradient magnitudes (None when ECC does not converge)."""
    b, sb = _scaled(before, params.ecc_pixels)
    a, sa = _scaled(after, params.ecc_pixels)

    def grad(g: NDArray[np.uint8]) -> NDArray[np.float32]:
        f = cv2.GaussianBlur(g.astype(np.float32), (0, 0), 1.0)
        return np.asarray(
            cv2.magnitude(cv2.Sobel(f, cv2.CV_32F, 1, 0), cv2.Sobel(f, cv2.CV_32F, 0, 1)),
            np.float32,
        )

    # ECC warps the input (BEFORE) into the template's (AFTER's) frame: its matrix maps
    # template pixels to input pixels, AFTER → BEFORE at the copies' scale
    Hs = np.diag([sb, sb, 1.0]) @ H @ np.diag([1 / sa, 1 / sa, 1.0])
    warp = (Hs / Hs[2, 2]).astype(np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, params.ecc_iterations, 1e-6)
    try:
        _, found = cv2.findTransformECC(
            grad(a),
            grad(b),
            warp,
            cv2.MOTION_HOMOGRAPHY,
            criteria,
            np.ones(a.shape, np.uint8),
            5,
        )
    except cv2.error:
        return None
    return _scale_h(np.asarray(found, np.float64), sa, sb)


def overlap_fraction(
    H: NDArray[np.float64], after_shape: tuple[int, ...], before_shape: tuple[int, ...]
) -> float:
    """Fraction of AFTER's pixels that ``H`` maps inside BEFORE."""
    h, w = after_shape[:2]
    step = max(1, max(h, w) // 400)
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    p = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]).astype(np.float64)
    q = H @ p
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = q[0] / q[2], q[1] / q[2]
    bh, bw = before_shape[:2]
    inside = (q[2] > 0) & (x >= -0.5) & (x <= bw - 0.5) & (y >= -0.5) & (y <= bh - 0.5)
    return float(inside.mean())


def _residual(H: NDArray[np.float64], pa: NDArray[np.float64], pb: NDArray[np.float64]) -> float:
    q = cv2.perspectiveTransform(pa.reshape(-1, 1, 2), H).reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum((q - pb) ** 2, axis=1))))


def align_visits(
    before: NDArray[np.uint8], after: NDArray[np.uint8], params: AlignParams = AlignParams()
) -> Alignment:
    """Align AFTER (H, W[, 3]) to BEFORE; AlignmentError when they share no surface."""
    gb, ga = _gray(before), _gray(after)
    H, pa, pb = feature_homography(gb, ga, params)
    refined = refine_ecc(gb, ga, H, params)
    if refined is not None and _residual(refined, pa, pb) <= _residual(H, pa, pb) + 1.0:
        H = refined
    H = H / H[2, 2]
    overlap = overlap_fraction(H, after.shape, before.shape)
    if overlap < params.min_overlap:
        raise AlignmentError(f"only {overlap:.0%} of AFTER lies inside BEFORE: not one surface")
    return Alignment(H, _residual(H, pa, pb), overlap, len(pa))


def world_transform(
    after_to_before: NDArray[np.float64],
    after_size: tuple[int, int],
    after_origin_m: tuple[float, float],
    after_px_per_m: float,
    before_origin_m: tuple[float, float],
    before_px_per_m: float,
) -> tuple[NDArray[np.float64], float]:
    """The planar pose (x, y, yaw) of AFTER's world frame in BEFORE's, from a homography
    between two mosaics (pixel (u, v) at world ``origin_m + (u, v) / px_per_m``), and the
    RMS distance (m) by which the rigid pose departs from the homography over AFTER."""
    w, h = after_size
    us, vs = np.meshgrid(np.linspace(0, w, 9), np.linspace(0, h, 9))
    pa = np.stack([us.ravel(), vs.ravel()], 1)
    pb = cv2.perspectiveTransform(pa.reshape(-1, 1, 2), after_to_before).reshape(-1, 2)
    wa = np.asarray(after_origin_m) + pa / after_px_per_m
    wb = np.asarray(before_origin_m) + pb / before_px_per_m
    T = umeyama_alignment(
        np.column_stack([wa, np.zeros(len(wa))]), np.column_stack([wb, np.zeros(len(wb))])
    )
    fit = wa @ T[:2, :2].T + T[:2, 3]
    rms = float(np.sqrt(np.mean(np.sum((fit - wb) ** 2, axis=1))))
    return np.array([T[0, 3], T[1, 3], np.arctan2(T[1, 0], T[0, 0])]), rms
