"""Crack and corrosion detection and the measurement of each defect (paper §3.3).

First version of the pipeline: cracks by morphological black-hat + Otsu + cleaning
(the ``proposed`` method until the paper's full pipeline lands), the paper's Otsu and
Sauvola baselines, rust areas by colour, and defects measured as objects.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from skimage.filters import threshold_sauvola
from skimage.morphology import skeletonize

Method = Literal["proposed", "otsu", "sauvola"]
METHODS: tuple[str, ...] = ("proposed", "otsu", "sauvola")


@dataclass(frozen=True)
class CrackParams:
    """Options of the crack detector (sizes in pixels)."""

    blackhat_px: int = 15
    min_area_px: int = 40
    min_length_px: float = 25.0
    min_elongation: float = 3.0
    min_contrast: float = 12.0
    sauvola_window: int = 25
    sauvola_k: float = 0.2


@dataclass(frozen=True)
class CorrosionParams:
    """Options of the rust detector."""

    hue_min: int = 0
    hue_max: int = 22
    min_saturation: int = 90
    min_area_px: int = 400


@dataclass(frozen=True)
class Defect:
    """One connected defect measured in pixels (and mm when the scale is known)."""

    id: int
    defect_class: str
    bbox: tuple[int, int, int, int]
    area_px: int
    length_px: float
    max_width_px: float
    mean_width_px: float
    orientation_deg: float
    centroid_px: tuple[float, float]
    length_mm: float | None = None
    max_width_mm: float | None = None
    area_mm2: float | None = None


def to_gray(image: NDArray[np.generic]) -> NDArray[np.uint8]:
    """8-bit grayscale of an 8/16-bit gray or BGR(A) image; raise ValueError otherwise."""
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if image.ndim != 2:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {image.shape}")
    if image.dtype == np.uint16:
        image = (image / 257.0).round().astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"image must be uint8 or uint16, got {image.dtype}")
    return image


def detect_cracks(image: NDArray[np.generic], *, method: Method = "proposed", params: CrackParams = CrackParams()) -> NDArray[np.bool_]:
    """Boolean (H, W) mask of crack pixels by the chosen method."""
    gray = to_gray(image)
    if gray.shape[0] < 3 or gray.shape[1] < 3:
        return np.zeros(gray.shape, bool)
    if method == "otsu":
        t, _ = cv2.threshold(gray, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        return gray < t if gray.max() > gray.min() else np.zeros(gray.shape, bool)
    if method == "sauvola":
        t = threshold_sauvola(gray, window_size=params.sauvola_window, k=params.sauvola_k)
        return gray < t
    if method != "proposed":
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return _blackhat_cracks(gray, params)


def _blackhat_cracks(gray: NDArray[np.uint8], params: CrackParams) -> NDArray[np.bool_]:
    k = params.blackhat_px | 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    smooth = cv2.GaussianBlur(gray, (3, 3), 0)
    blackhat = cv2.morphologyEx(smooth, cv2.MORPH_BLACKHAT, kernel)
    if int(blackhat.max()) < params.min_contrast:
        return np.zeros(gray.shape, bool)
    t, _ = cv2.threshold(blackhat, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    mask = blackhat > max(t, params.min_contrast)
    mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0
    return _keep_line_like(mask, params)


def _keep_line_like(mask: NDArray[np.bool_], params: CrackParams) -> NDArray[np.bool_]:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = np.zeros(n, bool)
    for i in range(1, n):
        x, y, w, h, area = stats[i]
        if area < params.min_area_px:
            continue
        extent = float(np.hypot(w, h))
        # a line's bounding-box diagonal is long compared with its mean width (area / extent)
        if extent >= params.min_length_px and extent * extent / area >= params.min_elongation:
            keep[i] = True
    return keep[labels]


def detect_corrosion(image: NDArray[np.generic], *, params: CorrosionParams = CorrosionParams()) -> NDArray[np.bool_]:
    """Boolean (H, W) mask of rust-coloured areas (needs a BGR image; gray gives none)."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        return np.zeros(image.shape[:2], bool)
    hsv = cv2.cvtColor(cv2.GaussianBlur(image, (5, 5), 0), cv2.COLOR_BGR2HSV)
    h, s = hsv[..., 0], hsv[..., 1]
    mask = (h >= params.hue_min) & (h <= params.hue_max) & (s >= params.min_saturation)
    mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= params.min_area_px
    keep[0] = False
    return keep[labels]


def measure_defects(
    mask: NDArray[np.bool_], defect_class: str, *, mm_per_px: float | None = None, first_id: int = 1
) -> list[Defect]:
    """Measure each connected component of ``mask`` as one defect.

    Length is the skeleton length (diagonal steps count √2); widths are ``2 d - 1``
    pixels for the distance transform ``d`` sampled on the skeleton (exact for straight lines); orientation is the principal axis angle
    in degrees from the image x axis.
    """
    m = mask.astype(np.uint8)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(m, connectivity=8)
    dist = cv2.distanceTransform(np.pad(m, 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    defects = []
    for i in range(1, n):
        x, y, w, h, area = (int(v) for v in stats[i])
        comp = labels[y : y + h, x : x + w] == i
        skel = skeletonize(comp)
        length = _skeleton_length(skel)
        widths = np.maximum(2.0 * dist[y : y + h, x : x + w][skel] - 1.0, 1.0) if skel.any() else np.array([1.0])
        ys, xs = np.nonzero(comp)
        orientation = _orientation_deg(xs, ys)
        d = Defect(
            id=first_id + len(defects),
            defect_class=defect_class,
            bbox=(x, y, w, h),
            area_px=area,
            length_px=round(length, 2),
            max_width_px=round(float(widths.max()), 2),
            mean_width_px=round(float(widths.mean()), 2),
            orientation_deg=round(orientation, 1),
            centroid_px=(float(centroids[i][0]), float(centroids[i][1])),
        )
        if mm_per_px is not None:
            d = _with_mm(d, mm_per_px)
        defects.append(d)
    return defects


def _with_mm(d: Defect, mm_per_px: float) -> Defect:
    return replace(
        d,
        length_mm=round(d.length_px * mm_per_px, 2),
        max_width_mm=round(d.max_width_px * mm_per_px, 3),
        area_mm2=round(d.area_px * mm_per_px**2, 2),
    )


def _skeleton_length(skel: NDArray[np.bool_]) -> float:
    """Skeleton length as a pixel path: orthogonal steps count 1, diagonal steps √2.

    A diagonal pair already joined through an orthogonal neighbour is not counted twice.
    """
    s = skel.astype(bool)
    if s.sum() <= 1:
        return float(s.sum())
    ortho = (s[:, 1:] & s[:, :-1]).sum() + (s[1:, :] & s[:-1, :]).sum()
    d1 = s[1:, 1:] & s[:-1, :-1] & ~s[:-1, 1:] & ~s[1:, :-1]
    d2 = s[1:, :-1] & s[:-1, 1:] & ~s[:-1, :-1] & ~s[1:, 1:]
    return float(ortho + np.sqrt(2) * (d1.sum() + d2.sum()))


def _orientation_deg(xs: NDArray[np.intp], ys: NDArray[np.intp]) -> float:
    if len(xs) < 2:
        return 0.0
    cov = np.cov(np.vstack([xs, ys]).astype(np.float64))
    evals, evecs = np.linalg.eigh(cov)
    vx, vy = evecs[:, np.argmax(evals)]
    return float(np.degrees(np.arctan2(vy, vx)) % 180.0)
