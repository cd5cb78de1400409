"""Global alignment of mosaic frames: every overlapping pair registered (rotation and
translation, ECC), then all frame poses solved together by least squares, so error does
not accumulate along the robot's path."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix


@dataclass(frozen=True)
class PairMeasurement:
    """Where three points of frame i's overlap with frame j fall in frame j (pixels)."""

    i: int
    j: int
    points_i: NDArray[np.float64]  # (3, 2) in frame i
    points_j: NDArray[np.float64]  # (3, 2) in frame j
    score: float


def frame_to_mosaic(pose: NDArray[np.floating], size: tuple[int, int]) -> NDArray[np.float64]:
    """3x3 matrix A mapping frame pixels to mosaic pixels for a pose (x, y, θ) of its centre."""
    w, h = size
    c, s = np.cos(pose[2]), np.sin(pose[2])
    cx, cy = (w - 1) / 2, (h - 1) / 2
    return np.array([[c, -s, pose[0] - c * cx + s * cy], [s, c, pose[1] - s * cx - c * cy], [0, 0, 1.0]])


def _gray32(img: NDArray[np.uint8]) -> NDArray[np.float32]:
    g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
    return g.astype(np.float32)


def overlap_rect(A_i: NDArray[np.float64], A_j: NDArray[np.float64], size: tuple[int, int], margin: int) -> tuple[int, int, int, int] | None:
    """Axis-aligned rectangle of frame i covered by frame j, shrunk by ``margin``."""
    w, h = size
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
    in_i = (np.linalg.inv(A_i) @ A_j @ corners)[:2]
    x0, y0 = max(0, int(np.ceil(in_i[0].min())) + margin), max(0, int(np.ceil(in_i[1].min())) + margin)
    x1, y1 = min(w, int(np.floor(in_i[0].max()))) - margin, min(h, int(np.floor(in_i[1].max()))) - margin
    if x1 - x0 < 48 or y1 - y0 < 48 or (x1 - x0) * (y1 - y0) < 0.08 * w * h:
        return None
    return x0, y0, x1, y1


def register_pair(
    gray_i: NDArray[np.float32], gray_j: NDArray[np.float32], A_i: NDArray[np.float64], A_j: NDArray[np.float64],
    *, margin: int = 16, min_score: float = 0.8, max_shift_px: float = 12.0, search_px: int = 48,
) -> PairMeasurement | None:
    """Refine the relative pose of two overlapping frames by ECC (Euclidean motion).

    A coarse translation search (±``search_px``) comes first, so odometry errors of tens
    of pixels are fine. Rejected when the correlation stays under ``min_score`` or ECC moved
    the overlap more than ``max_shift_px`` from the coarse result (it ran away).
    """
    h, w = gray_i.shape
    rect = overlap_rect(A_i, A_j, (w, h), margin)
    if rect is None:
        return None
    x0, y0, x1, y1 = rect
    template = gray_i[y0:y1, x0:x1]
    if float(template.std()) < 2.0:
        return None  # no texture to register on
    # coarse: the best translation within ±search_px by normalised cross-correlation of the
    # overlap, frame j seen through the initial poses; fine: ECC from there
    i_to_j = np.linalg.inv(A_j) @ A_i
    seen_j = cv2.warpAffine(gray_j, i_to_j[:2], (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    s = min(search_px, (x1 - x0 - 16) // 2, (y1 - y0 - 16) // 2)
    shift = np.zeros(2)
    if s >= 4:
        res = cv2.matchTemplate(seen_j[y0:y1, x0:x1], template[s:-s, s:-s], cv2.TM_CCOEFF_NORMED)
        _, _, _, (bx, by) = cv2.minMaxLoc(res)
        shift = np.array([bx - s, by - s], float)
    # ECC between the overlap and frame j already turned into frame i's orientation (its
    # Euclidean model only converges from near-identity warps, not from a 180° turn)
    W = np.array([[1, 0, x0 + shift[0]], [0, 1, y0 + shift[1]]], np.float32)
    W0 = W.astype(np.float64).copy()
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 60, 1e-5)
    try:
        score, W = cv2.findTransformECC(template, seen_j, W, cv2.MOTION_EUCLIDEAN, criteria, None, 5)
    except cv2.error:
        return None
    if score < min_score:
        return None
    pts = np.array([[x0 + 0.2 * (x1 - x0), y0 + 0.2 * (y1 - y0)], [x1 - 0.2 * (x1 - x0), y0 + 0.2 * (y1 - y0)],
                    [x0 + 0.5 * (x1 - x0), y1 - 0.2 * (y1 - y0)]])
    local = pts - (x0, y0)
    in_seen = local @ W[:, :2].T.astype(np.float64) + W[:, 2]
    if np.abs(in_seen - (local @ W0[:, :2].T + W0[:, 2])).max() > max_shift_px:
        return None
    in_j = (i_to_j @ np.column_stack([in_seen, np.ones(3)]).T)[:2].T
    return PairMeasurement(0, 0, pts, in_j, float(score))


def candidate_pairs(poses: NDArray[np.float64], size: tuple[int, int]) -> list[tuple[int, int]]:
    """Pairs of frames whose centres are close enough for their footprints to overlap
    (the overlap itself is checked when the pair is registered)."""
    reach = 0.95 * max(size)
    out = []
    for i in range(len(poses)):
        d = np.linalg.norm(poses[i + 1 :, :2] - poses[i, :2], axis=1)
        out += [(i, i + 1 + k) for k in np.nonzero(d < reach)[0]]
    return out


def optimise_poses(
    initial: NDArray[np.float64], measurements: Sequence[PairMeasurement], size: tuple[int, int], *, prior_weight: float = 0.001,
) -> NDArray[np.float64]:
    """Least-squares poses (N, 3): pair measurements, plus a weak pull towards the initial
    relative motion of consecutive frames (keeps frames without matches in place).
    Frame 0 stays fixed."""
    n = len(initial)
    if n < 2:
        return initial.copy()

    def unpack(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.vstack([initial[:1], x.reshape(n - 1, 3)])

    rel0 = [np.linalg.inv(frame_to_mosaic(initial[k], size)) @ frame_to_mosaic(initial[k + 1], size) for k in range(n - 1)]
    probe = np.array([[0, 0, 1], [size[0] - 1, size[1] - 1, 1.0]]).T

    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:
        poses = unpack(x)
        A = [frame_to_mosaic(p, size) for p in poses]
        res = []
        for m in measurements:
            pts_i = np.column_stack([m.points_i, np.ones(3)]).T
            pred = (np.linalg.inv(A[m.j]) @ A[m.i] @ pts_i)[:2].T
            res.append((pred - m.points_j).ravel())
        for k in range(n - 1):
            pred = np.linalg.inv(A[k]) @ A[k + 1] @ probe
            res.append(prior_weight * (pred - rel0[k] @ probe)[:2].ravel())
        return np.concatenate(res)

    sparsity = lil_matrix((6 * len(measurements) + 4 * (n - 1), 3 * (n - 1)), dtype=int)
    row = 0
    for m in measurements:
        for k in (m.i, m.j):
            if k > 0:
                sparsity[row : row + 6, 3 * (k - 1) : 3 * k] = 1
        row += 6
    for k in range(n - 1):
        for kk in (k, k + 1):
            if kk > 0:
                sparsity[row : row + 4, 3 * (kk - 1) : 3 * kk] = 1
        row += 4
    # a robust loss: one wrong pair cannot pull the whole mosaic apart
    sol = least_squares(residuals, initial[1:].ravel(), jac_sparsity=sparsity, method="trf", x_scale="jac",
                        loss="soft_l1", f_scale=2.0)
    return unpack(sol.x)


def align_frames(frames: Sequence[NDArray[np.uint8]], initial: NDArray[np.float64]) -> tuple[NDArray[np.float64], int, NDArray[np.bool_]]:
    """Globally aligned poses (N, 3) in mosaic pixels / radians from an initial placement;
    also the number of registered pairs and which frames took part in at least one."""
    h, w = frames[0].shape[:2]
    grays = [_gray32(f) for f in frames]
    measurements = []
    for i, j in candidate_pairs(initial, (w, h)):
        m = register_pair(grays[i], grays[j], frame_to_mosaic(initial[i], (w, h)), frame_to_mosaic(initial[j], (w, h)))
        if m is not None:
            measurements.append(PairMeasurement(i, j, m.points_i, m.points_j, m.score))
    linked = np.zeros(len(frames), bool)
    for m in measurements:
        linked[[m.i, m.j]] = True
    if not measurements:
        return initial.copy(), 0, linked
    return optimise_poses(initial, measurements, (w, h)), len(measurements), linked
