"""Two visits made from one photograph of a crack, with the truth known: BEFORE is the
photograph with the far part of a crack painted out (the crack grew by that much since),
AFTER is the whole photograph seen again from a shifted, turned and rescaled viewpoint
under other lighting. For measuring :mod:`.align` and :mod:`.changes` on real images."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from skimage.morphology import skeletonize

from processing.detection.defects import skeleton_length


@dataclass(frozen=True)
class VisitPair:
    """BEFORE and AFTER images, the true AFTER → BEFORE homography, and the crack's true
    growth (AFTER's pixels) with where it grew (AFTER's pixels, x, y, w, h) and its whole
    length on AFTER."""

    before: NDArray[np.uint8]
    after: NDArray[np.uint8]
    after_to_before: NDArray[np.float64]
    growth_px: float
    grown_box_after: tuple[int, int, int, int]
    length_after_px: float


def _longest_crack(mask: NDArray[np.bool_]) -> NDArray[np.bool_] | None:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n < 2:
        return None
    i = 1 + int(np.argmax(np.maximum(stats[1:, cv2.CC_STAT_WIDTH], stats[1:, cv2.CC_STAT_HEIGHT])))
    return np.asarray(labels == i)


def paint_out_tip(
    image: NDArray[np.uint8], crack: NDArray[np.bool_], fraction: float
) -> tuple[NDArray[np.uint8], NDArray[np.bool_], float]:
    """``image`` with the ``fraction`` of ``crack`` farthest along its main axis painted out
    (inpainted from its surroundings); the part removed and its skeleton length."""
    ys, xs = np.nonzero(crack)
    pts = np.stack([xs, ys], 1).astype(np.float64)
    centre = pts.mean(0)
    _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
    along = (pts - centre) @ vt[0]
    cut = np.quantile(along, 1 - fraction)
    tip = np.zeros_like(crack)
    tip[ys[along > cut], xs[along > cut]] = True
    removed = skeleton_length(skeletonize(tip))
    paint = cv2.dilate(tip.astype(np.uint8), np.ones((7, 7), np.uint8))
    return np.asarray(cv2.inpaint(image, paint, 5, cv2.INPAINT_TELEA), np.uint8), tip, removed


def viewpoint(
    size: tuple[int, int], angle_deg: float, scale: float, shift_px: tuple[float, float]
) -> NDArray[np.float64]:
    """BEFORE → AFTER similarity (3, 3) about the image centre."""
    w, h = size
    M = np.asarray(cv2.getRotationMatrix2D((w / 2, h / 2), angle_deg, scale), np.float64)
    M[:, 2] += np.asarray(shift_px, np.float64)
    return np.vstack([M, [0.0, 0.0, 1.0]])


def make_pair(
    image: NDArray[np.uint8], mask: NDArray[np.bool_], rng: np.random.Generator
) -> VisitPair | None:
    """A pair from ``image`` (H, W, 3) and its crack ``mask`` (H, W); None when the image
    holds no crack long enough to cut. Turn ±10°, scale ±5 %, shift up to 12 % of the
    size, gain 0.7-1.3, gamma 0.8-1.25, a little noise."""
    crack = _longest_crack(mask)
    h, w = mask.shape
    if crack is None or max(
        np.ptp(np.nonzero(crack)[0]), np.ptp(np.nonzero(crack)[1])
    ) < 0.25 * min(h, w):
        return None
    before, tip, removed = paint_out_tip(image, crack, rng.uniform(0.2, 0.4))
    for _ in range(20):  # a viewpoint from which the grown part is seen whole
        B2A = viewpoint(
            (w, h),
            rng.uniform(-10, 10),
            rng.uniform(0.95, 1.05),
            tuple(rng.uniform(-0.12, 0.12, 2) * (w, h)),
        )
        ys, xs = np.nonzero(tip)
        q = cv2.perspectiveTransform(np.float64(np.stack([xs, ys], 1)).reshape(-1, 1, 2), B2A)
        q = q.reshape(-1, 2)
        if ((q >= 8) & (q < np.array([w, h]) - 8)).all(axis=1).mean() > 0.98:
            break
    else:
        return None
    after = cv2.warpPerspective(
        image, B2A, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
    )
    g = rng.uniform(0.7, 1.3)
    gamma = rng.uniform(0.8, 1.25)
    lit = 255.0 * np.clip(g * (after.astype(np.float32) / 255.0) ** gamma, 0, 1)
    lit += rng.normal(0, 2.0, lit.shape)
    after = np.clip(lit, 0, 255).astype(np.uint8)
    tip_after = cv2.warpPerspective(tip.astype(np.uint8), B2A, (w, h), flags=cv2.INTER_NEAREST)
    ys, xs = np.nonzero(tip_after)
    box = (
        (int(xs.min()), int(ys.min()), int(np.ptp(xs)) + 1, int(np.ptp(ys)) + 1)
        if len(xs)
        else (0, 0, 0, 0)
    )
    scale = float(np.sqrt(abs(np.linalg.det(B2A[:2, :2]))))
    A2B = np.asarray(np.linalg.inv(B2A), np.float64)
    length = skeleton_length(skeletonize(crack)) * scale
    return VisitPair(np.asarray(before, np.uint8), after, A2B, removed * scale, box, length)


def corner_error_px(
    H: NDArray[np.float64], truth: NDArray[np.float64], size: tuple[int, int]
) -> float:
    """Mean distance (px) between where ``H`` and ``truth`` put AFTER's corners."""
    w, h = size
    c = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64).reshape(-1, 1, 2)
    a = cv2.perspectiveTransform(c, H).reshape(-1, 2)
    b = cv2.perspectiveTransform(c, truth).reshape(-1, 2)
    return float(np.linalg.norm(a - b, axis=1).mean())
