"""Accuracy metrics: the paper's PI, SI, DSC (eqs. (18)–(20)), ATE, and defect matching."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class SegmentationScores:
    """Pixel-wise precision (PI), sensitivity (SI) and Dice (DSC)."""

    pi: float
    si: float
    dsc: float


def segmentation_scores(
    pred: NDArray[np.bool_], truth: NDArray[np.bool_], *, tolerance_px: int = 0
) -> SegmentationScores:
    """PI = TP/(TP+FP), SI = TP/(TP+FN), DSC = 2TP/(2TP+FP+FN) (paper eqs. (18)–(20)).

    With ``tolerance_px`` > 0 a predicted pixel counts as true within that distance of a
    true pixel, and a true pixel as found within that distance of a predicted one.
    """
    if pred.shape != truth.shape:
        raise ValueError(f"pred {pred.shape} and truth {truth.shape} differ in shape")
    p, t = pred.astype(bool), truth.astype(bool)
    if tolerance_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * tolerance_px + 1,) * 2)
        t_near = cv2.dilate(t.astype(np.uint8), k) > 0
        p_near = cv2.dilate(p.astype(np.uint8), k) > 0
        tp_p, fp = int((p & t_near).sum()), int((p & ~t_near).sum())
        tp_t, fn = int((t & p_near).sum()), int((t & ~p_near).sum())
    else:
        tp_p = tp_t = int((p & t).sum())
        fp, fn = int((p & ~t).sum()), int((~p & t).sum())
    pi = tp_p / (tp_p + fp) if tp_p + fp else (1.0 if not t.any() else 0.0)
    si = tp_t / (tp_t + fn) if tp_t + fn else 1.0
    dsc = (
        2 * pi * si / (pi + si)
        if tolerance_px > 0 and pi + si
        else (2 * tp_p / (2 * tp_p + fp + fn) if 2 * tp_p + fp + fn else 1.0)
    )
    return SegmentationScores(round(pi, 6), round(si, 6), round(dsc, 6))


@dataclass
class PooledCounts:
    """Pixel counts pooled over many images (the benchmark's way of scoring a set):
    predicted pixels near truth / not, true pixels found / missed."""

    tolerance_px: int = 0
    tp_pred: int = 0
    fp: int = 0
    tp_true: int = 0
    fn: int = 0

    def add(self, pred: NDArray[np.bool_], truth: NDArray[np.bool_]) -> None:
        """Accumulate one (H, W) prediction against its (H, W) truth."""
        if pred.shape != truth.shape:
            raise ValueError(f"pred {pred.shape} and truth {truth.shape} differ in shape")
        p, t = pred.astype(bool), truth.astype(bool)
        if self.tolerance_px > 0:
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * self.tolerance_px + 1,) * 2)
            t_near = cv2.dilate(t.view(np.uint8), k) > 0
            p_near = cv2.dilate(p.view(np.uint8), k) > 0
        else:
            t_near, p_near = t, p
        self.tp_pred += int(np.count_nonzero(p & t_near))
        self.fp += int(np.count_nonzero(p & ~t_near))
        self.tp_true += int(np.count_nonzero(t & p_near))
        self.fn += int(np.count_nonzero(t & ~p_near))

    def scores(self) -> SegmentationScores:
        """PI, SI and DSC (eqs. (18)–(20)) of the pooled counts; DSC as the harmonic mean
        of PI and SI, which equals eq. (20) when there is no tolerance."""
        pi = self.tp_pred / max(self.tp_pred + self.fp, 1)
        si = self.tp_true / max(self.tp_true + self.fn, 1)
        dsc = 2 * pi * si / (pi + si) if pi + si else 0.0
        return SegmentationScores(round(pi, 4), round(si, 4), round(dsc, 4))


def umeyama_alignment(src: NDArray[np.floating], dst: NDArray[np.floating]) -> NDArray[np.float64]:
    """4x4 rigid transform (no scale) minimising ||T·src - dst|| over (N, 3) point sets."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_d - R @ mu_s
    return T


def absolute_trajectory_error(
    est: NDArray[np.floating], gt: NDArray[np.floating], *, align: bool = True
) -> float:
    """RMSE in metres of trajectory positions (N, 4, 4) after rigid alignment (TUM ATE)."""
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"est {est.shape} and gt {gt.shape} must both be (N, 4, 4)")
    pe, pg = est[:, :3, 3], gt[:, :3, 3]
    if align and len(pe) >= 3:
        T = umeyama_alignment(pe, pg)
        pe = pe @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((pe - pg) ** 2, axis=1))))


@dataclass(frozen=True)
class Box:
    """An axis-aligned box in world metres with a defect class."""

    defect_class: str
    x: float
    y: float
    w: float
    h: float


def _overlaps(f: Box, t: Box, margin_m: float) -> bool:
    """Whether ``f`` and ``t`` are of one class and their boxes meet within ``margin_m``."""
    return (
        f.defect_class == t.defect_class
        and f.x <= t.x + t.w + margin_m
        and t.x <= f.x + f.w + margin_m
        and f.y <= t.y + t.h + margin_m
        and t.y <= f.y + f.h + margin_m
    )


def match_defects(found: Sequence[Box], truth: Sequence[Box], *, margin_m: float = 0.01) -> int:
    """Number of true defects overlapped (within ``margin_m``) by a found defect of their class."""
    return sum(any(_overlaps(f, t, margin_m) for f in found) for t in truth)


@dataclass(frozen=True)
class DefectAccount:
    """Found defects against true ones, from both sides.

    ``matched``: true defects some found defect overlaps (recall = matched / true);
    ``on_true``: found defects that overlap a true one (precision = on_true / found), of
    which ``pieces`` are second and further found defects given to one true defect (a
    crack found in pieces); ``false_alarms``: found defects on no true defect.
    """

    found: int
    true: int
    matched: int
    on_true: int
    pieces: int
    false_alarms: int

    @property
    def recall(self) -> float:
        """Share of the true defects found (1 when there are none)."""
        return self.matched / self.true if self.true else 1.0

    @property
    def precision(self) -> float:
        """Share of the found defects that lie on a true one (1 when none were found)."""
        return self.on_true / self.found if self.found else 1.0


def account_defects(
    found: Sequence[Box], truth: Sequence[Box], *, margin_m: float = 0.01
) -> DefectAccount:
    """Recall and precision of ``found`` against ``truth`` (boxes overlapping within
    ``margin_m``, same class), with the extra found defects told apart: each found defect
    on a true one is given to the true defect it overlaps most, and every one beyond the
    first a true defect gets is a further piece; the rest are false alarms."""
    owner: list[int] = []
    for f in found:
        hits = [i for i, t in enumerate(truth) if _overlaps(f, t, margin_m)]
        if hits:
            owner.append(max(hits, key=lambda i: _shared_area(f, truth[i])))
    matched = match_defects(found, truth, margin_m=margin_m)
    per_true = np.bincount(np.array(owner, int), minlength=len(truth)).tolist() if owner else []
    return DefectAccount(
        found=len(found),
        true=len(truth),
        matched=matched,
        on_true=len(owner),
        pieces=int(sum(max(0, int(k) - 1) for k in per_true)),
        false_alarms=len(found) - len(owner),
    )


def _shared_area(a: Box, b: Box) -> float:
    """Area (m²) the two boxes share."""
    w = min(a.x + a.w, b.x + b.w) - max(a.x, b.x)
    h = min(a.y + a.h, b.y + b.h) - max(a.y, b.y)
    return max(0.0, w) * max(0.0, h)


def mosaic_overlap_errors(
    est: NDArray[np.floating], truth: NDArray[np.floating], size: tuple[int, int]
) -> tuple[NDArray[np.float64], float]:
    """How far (px, worst frame corner) the estimated relative placement of every pair of
    truly overlapping frames is from the true one, and the end drift (first frame to last).

    ``est`` and ``truth`` are (N, 3) frame poses (centre x, y in pixels, rotation in
    radians) in any two frames of reference: only relative placements are compared.
    """
    from processing.poses import frame_to_mosaic

    w, h = size
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T

    def err(i: int, j: int) -> float:
        rel_e = np.linalg.inv(frame_to_mosaic(est[i], size)) @ frame_to_mosaic(est[j], size)
        rel_t = np.linalg.inv(frame_to_mosaic(truth[i], size)) @ frame_to_mosaic(truth[j], size)
        return float(np.linalg.norm((rel_e @ corners - rel_t @ corners)[:2], axis=0).max())

    out = [
        err(i, j)
        for i in range(len(truth))
        for j in range(i + 1, len(truth))
        if abs(truth[j, 0] - truth[i, 0]) < 0.9 * w and abs(truth[j, 1] - truth[i, 1]) < 0.9 * h
    ]
    return np.array(out), (err(0, len(truth) - 1) if len(truth) > 1 else 0.0)
