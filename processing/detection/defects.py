"""Defects as objects: each connected region of a defect mask measured (paper §4, DSC aside).

Bounding box, area, skeleton length, maximum and mean width from the distance transform,
orientation, and the same in millimetres when the image scale is known.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray
from skimage.morphology import skeletonize

from processing.detection.confidence import Calibration, component_features
from processing.detection.labels import component_stats


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
    confidence: float | None = None  # calibrated P(a true defect); None: the method has none


# the smallest defect a camera resolves, in its pixels: a crack shorter than this, a rust
# patch smaller than its square, is a speck, not a defect anyone can assess
RESOLVED_PX = 3.0


def resolved(d: Defect) -> bool:
    """Whether ``d`` is at least :data:`RESOLVED_PX` pixels long (a crack) or that squared
    in area (anything else)."""
    if d.defect_class == "crack":
        return d.length_px >= RESOLVED_PX
    return d.area_px >= RESOLVED_PX**2


@dataclass(frozen=True)
class Components:
    """Labelled 8-connected components of a mask (``cv2.connectedComponentsWithStats``)
    and which of them are defects (label 0, the background, never is)."""

    labels: NDArray[np.int32]
    stats: NDArray[np.int32]
    centroids: NDArray[np.float64]
    keep: NDArray[np.bool_]

    @classmethod
    def of(cls, mask: NDArray[np.bool_]) -> Components:
        """Every component of ``mask``: OpenCV's labelling, statistics in one compiled pass."""
        n, found = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
        labels = cast(NDArray[np.int32], found)
        stats, centroids = component_stats(labels, n)
        keep = np.ones(n, bool)
        keep[0] = False
        return cls(labels, stats, centroids, keep)


def measure_defects(
    mask: NDArray[np.bool_],
    defect_class: str,
    *,
    mm_per_px: float | None = None,
    first_id: int = 1,
    contrast: NDArray[np.floating] | None = None,
    components: Components | None = None,
    probability: NDArray[np.floating] | None = None,
    calibration: Calibration | None = None,
) -> list[Defect]:
    """Measure each connected component of ``mask`` as one defect.

    Length is the skeleton length (diagonal steps count √2); widths are ``2 d - 1``
    pixels for the distance transform ``d`` sampled on the skeleton (exact for straight
    lines); orientation is the principal axis angle in degrees from the image x axis.
    With ``contrast`` (how much darker than its surroundings each pixel is), widths are
    taken at half the defect's peak contrast (full width at half maximum), so the blurred
    rim a detector includes does not widen the crack. ``components`` of ``mask`` may be
    given when already labelled (they must be exactly its components). With the network's
    ``probability`` map and its ``calibration``, each defect gets its calibrated
    confidence (:mod:`processing.detection.confidence`).
    """
    if contrast is not None and contrast.shape != mask.shape:
        raise ValueError(f"contrast {contrast.shape} and mask {mask.shape} differ in shape")
    comps = components if components is not None else Components.of(mask)
    labels, stats, centroids = comps.labels, comps.stats, comps.centroids
    confidence = None
    if probability is not None and calibration is not None:
        feats = component_features(probability, labels, len(comps.keep))
        confidence = calibration.confidence(feats)
    defects: list[Defect] = []
    for i in np.flatnonzero(comps.keep).tolist():
        x, y, w, h, area = (int(v) for v in stats[i])
        comp = labels[y : y + h, x : x + w] == i
        skel = skeletonize(comp)
        length = skeleton_length(skel)
        core = comp
        if contrast is not None:
            c = contrast[y : y + h, x : x + w]
            core = comp & (c >= 0.5 * float(c[comp].max()))
        # each component on its own: widths never see a neighbour
        dist = cv2.distanceTransform(np.pad(core.astype(np.uint8), 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
        d_skel = dist[skel]
        d_skel = d_skel[d_skel > 0] if (d_skel > 0).any() else d_skel
        widths = np.maximum(2.0 * d_skel - 1.0, 1.0) if d_skel.size else np.array([1.0])
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
            confidence=round(float(confidence[i]), 3) if confidence is not None else None,
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


def skeleton_length(skel: NDArray[np.bool_]) -> float:
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


def seam_links(above: NDArray[np.integer], below: NDArray[np.integer]) -> set[tuple[int, int]]:
    """Pairs ``(label above, label below)`` of components that touch (8-connected) across the
    seam between the last row of one band's labels (``above``) and the first row of the next
    (``below``); 0 is background."""
    links: set[tuple[int, int]] = set()
    w = len(above)
    for dx in (-1, 0, 1):
        a = above[max(0, -dx) : w - max(0, dx)]
        b = below[max(0, dx) : w - max(0, -dx)]
        both = (a > 0) & (b > 0)
        links.update(zip(a[both].tolist(), b[both].tolist()))
    return links


def moved(d: Defect, dx: int, dy: int, new_id: int) -> Defect:
    """The defect ``d`` measured on a crop, placed back at offset (dx, dy) with a new id."""
    x, y, w, h = d.bbox
    return replace(
        d,
        id=new_id,
        bbox=(x + dx, y + dy, w, h),
        centroid_px=(d.centroid_px[0] + dx, d.centroid_px[1] + dy),
    )
