"""Frame-to-frame registration and global pose estimation for mosaics.

Every pair of frames that overlaps is registered (coarse normalised cross-correlation,
then sub-pixel Lucas–Kanade with rotation), and all frame poses are solved together as a 2D pose
graph (robust Gauss-Newton), so error does not accumulate along the robot's path. Without
odometry, the first guesses come from phase correlation (:mod:`processing.phase`).

A pose is (x, y, θ): the frame centre in mosaic pixels and the angle from the mosaic's
x axis to the frame's x axis (radians, positive from x towards y).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from itertools import pairwise

import cv2
import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import spsolve

from processing.phase import PHASE_SCALES, QUARTER_TURNS, Gray, PhaseView, phase_candidates
from processing.poses import wrap_angle


@dataclass(frozen=True)
class RegistrationParams:
    """Options of pairwise registration and the pose graph."""

    search_px: int = 40  # coarse translation search radius (full-resolution pixels)
    margin_px: int = 8
    min_overlap: float = 0.15  # of the frame area (diagonal lane neighbours add little)
    min_texture: float = 1.5  # grey-level standard deviation of the overlap
    min_score: float = 0.75  # correlation coefficient of the matched pixels
    max_refine_px: float = 6.0  # the refinement may move the overlap this far from the coarse match
    max_refine_rad: float = 0.05  # ... and turn it this far
    points: int = 3000  # pixels used by the sub-pixel refinement
    half_stage_below: float = 0.9  # refine at half resolution first when the coarse correlation is weaker
    iterations: int = 30
    lever_px: float = 200.0  # weight of a heading residual: radians times this, as pixels
    prior_weight: float = 0.01  # odometry steps, relative to image measurements
    huber_px: float = 1.0
    max_residual_px: float = 3.0  # pairs off by more after the first solve are dropped
    workers: int = 2


@dataclass(frozen=True)
class PairMeasurement:
    """Relative pose of frame j in frame i's centred coordinates, measured from the images."""

    i: int
    j: int
    delta: NDArray[np.float64]  # (dx, dy, dθ)
    score: float
    mean_i: float  # mean grey of the overlap in frame i
    mean_j: float  # ... and of the same surface in frame j


@dataclass
class PoseEstimate:
    """Solved poses, which frames are held by image measurements, and the pairs used."""

    poses: NDArray[np.float64]
    confident: NDArray[np.bool_]
    measurements: list[PairMeasurement]
    rejected: int


def _rot(theta: float) -> NDArray[np.float64]:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def relative_pose(pose_i: NDArray[np.floating], pose_j: NDArray[np.floating]) -> NDArray[np.float64]:
    """Pose of j in i's frame: (R_iᵀ (t_j - t_i), θ_j - θ_i)."""
    d = _rot(float(pose_i[2])).T @ (np.asarray(pose_j[:2], float) - np.asarray(pose_i[:2], float))
    return np.array([d[0], d[1], float(wrap_angle(pose_j[2] - pose_i[2]))])


def compose_pose(pose_i: NDArray[np.floating], delta: NDArray[np.floating]) -> NDArray[np.float64]:
    """Pose of j from pose i and j's pose in i's frame (inverse of :func:`relative_pose`)."""
    t = np.asarray(pose_i[:2], float) + _rot(float(pose_i[2])) @ np.asarray(delta[:2], float)
    return np.array([t[0], t[1], float(wrap_angle(pose_i[2] + delta[2]))])


def frame_to_mosaic(pose: NDArray[np.floating], size: tuple[int, int]) -> NDArray[np.float64]:
    """3x3 matrix mapping frame pixels to mosaic pixels for a frame of ``size`` (w, h)."""
    w, h = size
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    R = _rot(float(pose[2]))
    return np.vstack([np.hstack([R, (np.asarray(pose[:2], float) - R @ c)[:, None]]), [0, 0, 1.0]])


def frame_i_to_j(delta: NDArray[np.floating], size: tuple[int, int]) -> NDArray[np.float64]:
    """3x3 map from frame-i pixels to frame-j pixels for j's relative pose ``delta``."""
    w, h = size
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    Rt = _rot(float(delta[2])).T
    return np.vstack([np.hstack([Rt, (c - Rt @ (c + np.asarray(delta[:2], float)))[:, None]]), [0, 0, 1.0]])


def delta_of_map(M: NDArray[np.float64], size: tuple[int, int]) -> NDArray[np.float64]:
    """Inverse of :func:`frame_i_to_j`: the relative pose of a frame-i → frame-j map."""
    w, h = size
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    phi = -np.arctan2(M[1, 0], M[0, 0])
    d = _rot(phi) @ (c - M[:2, 2]) - c
    return np.array([d[0], d[1], phi])




def _quarter_turn(k: int, size: tuple[int, int]) -> NDArray[np.float64]:
    """3x3 pixel map of ``cv2.rotate`` by k quarter turns clockwise on screen, for (w, h)."""
    w, h = size
    return [np.eye(3), np.array([[0, -1, h - 1], [1, 0, 0], [0, 0, 1.0]]),
            np.array([[-1, 0, w - 1], [0, -1, h - 1], [0, 0, 1.0]]), np.array([[0, 1, 0], [-1, 0, w - 1], [0, 0, 1.0]])][k]


def overlap_rect(M: NDArray[np.float64], size: tuple[int, int], margin: int, min_overlap: float) -> tuple[int, int, int, int] | None:
    """Axis-aligned rectangle of frame i that frame j covers (via the i→j map ``M``), shrunk
    by ``margin``; None when smaller than ``min_overlap`` of the frame."""
    w, h = size
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
    in_i = (np.linalg.inv(M) @ corners)[:2]
    # the largest axis-aligned box inside the (slightly rotated) footprint: inner corners
    xs, ys = np.sort(in_i[0]), np.sort(in_i[1])
    x0, x1 = max(0, int(np.ceil(xs[1])) + margin), min(w, int(np.floor(xs[2]))) - margin
    y0, y1 = max(0, int(np.ceil(ys[1])) + margin), min(h, int(np.floor(ys[2]))) - margin
    if x1 - x0 < 32 or y1 - y0 < 32 or (x1 - x0) * (y1 - y0) < min_overlap * w * h:
        return None
    return x0, y0, x1, y1


def _strong_points(mag: NDArray[np.float32], n: int, cells: int = 6) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """About ``n`` pixels (x, y) of strong gradient, spread over a ``cells`` x ``cells`` grid:
    in each cell, the strongest of every other pixel (neighbours carry the same information)."""
    sub = mag[::2, ::2]
    h, w = sub.shape
    ch, cw = h // cells, w // cells
    per = int(min(max(1, n // (cells * cells)), ch * cw))
    blocks = sub[: ch * cells, : cw * cells].reshape(cells, ch, cells, cw).transpose(0, 2, 1, 3).reshape(cells * cells, ch * cw)
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
        return cls(cv2.GaussianBlur(gray, (5, 5), sigma))  # truncated at 2σ: cheaper, as good for registration

    def crop(self, x0: int, y0: int, x1: int, y1: int) -> Smoothed:
        """A rectangle of it."""
        return Smoothed(self.image[y0:y1, x0:x1])


def refine_euclidean(
    template: Smoothed, image: Gray, W0: NDArray[np.float64], *, points: int = 4000, iterations: int = 30,
) -> tuple[NDArray[np.float64], float, float, float]:
    """Sub-pixel Euclidean warp (2x3, template pixel → image pixel) by inverse-compositional
    Lucas–Kanade (Baker & Matthews 2004) on the template's strongest-gradient pixels, with a
    gain and offset between the two images estimated at every step (exposure changes).
    Both images are smoothed alike beforehand (:class:`Smoothed`). Returns the warp, the
    correlation coefficient of the matched pixels and their mean grey level in the template
    and in the image."""
    gx = cv2.Sobel(template.image, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(template.image, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    mag = cv2.magnitude(gx, gy)
    mag[:2], mag[-2:], mag[:, :2], mag[:, -2:] = 0, 0, 0, 0
    xs, ys = _strong_points(mag, points)
    h, w = mag.shape
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    X, Y = xs - c[0], ys - c[1]
    Gx, Gy = gx[ys, xs].astype(np.float64), gy[ys, xs].astype(np.float64)
    SD = np.column_stack([Gx * -Y + Gy * X, Gx, Gy])  # steepest-descent images (θ about the centre, tx, ty)
    H_inv = np.linalg.inv(SD.T @ SD)
    Tv = template.image[ys, xs].astype(np.float64)
    Tc = Tv - Tv.mean()
    t_var = float(Tc @ Tc)
    W = np.vstack([W0, [0, 0, 1]]).astype(np.float64)
    Iw = np.empty(len(xs))
    _lk_iterate(np.asarray(image, dtype=np.float32), xs.astype(np.float64), ys.astype(np.float64), SD, H_inv, Tc,
                t_var, float(c[0]), float(c[1]), float(max(w, h)), W, Iw, iterations)
    Ic = Iw - Iw.mean()
    score = float(Ic @ Tc) / max(float(np.sqrt((Ic @ Ic) * t_var)), 1e-12)
    return W[:2], score, float(Tv.mean()), float(Iw.mean())


@numba.njit(nogil=True, cache=True, inline="always")
def _cubic(t: float) -> tuple[float, float, float, float]:  # pragma: no cover - compiled
    """Keys' cubic convolution weights (a = -0.5) of the samples at -1, 0, 1, 2 for offset t."""
    t2 = t * t
    t3 = t2 * t
    return (-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1.0, -1.5 * t3 + 2.0 * t2 + 0.5 * t, 0.5 * t3 - 0.5 * t2)


@numba.njit(nogil=True, cache=True, inline="always")
def _sample(image: Gray, qx: float, qy: float, rows: int, cols: int) -> float:  # pragma: no cover - compiled
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
def _lk_iterate(image: Gray, xs: NDArray[np.float64], ys: NDArray[np.float64], SD: NDArray[np.float64], H_inv: NDArray[np.float64],
                Tc: NDArray[np.float64], t_var: float, cx: float, cy: float, extent: float, W: NDArray[np.float64],
                Iw: NDArray[np.float64], iterations: int) -> None:  # pragma: no cover - compiled
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


FIRST_SEARCH_PX = 12  # the coarse search's first radius (full-resolution pixels)
EARLY_OVERLAP = 0.9  # pairs guessed to overlap less than this share of ``min_overlap`` are not searched
SIGMA = 1.0  # smoothing of both images before Lucas-Kanade (its convergence basin)


@dataclass(frozen=True)
class Level:
    """A frame prepared for registration: smoothed grey image at full and half resolution."""

    full: Smoothed
    half: Smoothed

    @classmethod
    def of(cls, gray: Gray) -> Level:
        """Prepare a full-resolution grey image."""
        gray = np.ascontiguousarray(gray, dtype=np.float32)
        return cls(Smoothed.of(gray, SIGMA), Smoothed.of(cv2.pyrDown(gray), SIGMA))

    @property
    def shape(self) -> tuple[int, int]:
        """(h, w) at full resolution."""
        return self.full.image.shape  # type: ignore[return-value]

    @property
    def nbytes(self) -> int:
        """Memory it holds."""
        return self.full.image.nbytes + self.half.image.nbytes


def _crop_for(image: Gray, W: NDArray[np.float64], tw: int, th: int, pad: int) -> tuple[Gray, NDArray[np.float64]]:
    """The part of ``image`` that a (tw x th) template reaches through warp ``W`` (plus
    ``pad``), and the warp into that part."""
    corners = W[:2] @ np.array([[0, 0, 1], [tw, 0, 1], [0, th, 1], [tw, th, 1]], float).T
    x0, y0 = (max(0, int(np.floor(v)) - pad) for v in corners.min(axis=1))
    x1, y1 = (int(np.ceil(v)) + pad for v in corners.max(axis=1))
    out = W[:2].copy()
    out[:, 2] -= (x0, y0)
    return image[y0 : min(y1, image.shape[0]), x0 : min(x1, image.shape[1])], out


def _uncrop(W: NDArray[np.float64], crop_W: NDArray[np.float64], crop_W0: NDArray[np.float64]) -> NDArray[np.float64]:
    out = W.copy()
    out[:, 2] += crop_W0[:, 2] - crop_W[:, 2]
    return out


def register_pair(
    frame_i: Level | Gray, frame_j: Level | Gray, guess: NDArray[np.floating], params: RegistrationParams = RegistrationParams(),
    *, angles: Sequence[float] = (0.0,),
) -> tuple[NDArray[np.float64], float, float, float] | None:
    """Relative pose of frame j in frame i's frame, refined from ``guess``.

    Frame j is first turned by whole quarter turns (exactly, no interpolation) so that the
    refinement starts near identity rotation; a coarse correlation search of
    ±``search_px`` at half resolution (at each of ``angles``, radians, added to the guessed
    rotation, when the rotation is uncertain) absorbs odometry errors; Lucas–Kanade on the half-
    and then the full-resolution image gives sub-pixel translation and rotation. Returns
    (delta, score, mean_i, mean_j), or None when the frames do not overlap enough, the
    overlap has no texture, or the match is weak or ran away.
    """
    li = frame_i if isinstance(frame_i, Level) else Level.of(frame_i)
    lj = frame_j if isinstance(frame_j, Level) else Level.of(frame_j)
    h, w = li.shape
    size = (w, h)
    M = frame_i_to_j(guess, size)
    if overlap_rect(M, size, params.margin_px, EARLY_OVERLAP * params.min_overlap) is None:
        return None  # too little overlap even allowing for the guess's error: not worth a search
    k = int(np.round(float(wrap_angle(guess[2])) / (np.pi / 2))) % 4
    j_full = lj.full.image if k == 0 else cv2.rotate(lj.full.image, QUARTER_TURNS[k])
    j_half = lj.half.image if k == 0 else cv2.rotate(lj.half.image, QUARTER_TURNS[k])
    Q = _quarter_turn(k, size)
    # coarse: a small search first (the guess is usually good); the full radius when its
    # peak is weak or on the search window's edge
    coarse, edge = 0.0, True
    if len(angles) == 1 and params.search_px > FIRST_SEARCH_PX:
        M_try, coarse, edge = _coarse_search(li, j_half, M, Q, size, FIRST_SEARCH_PX, params, angles)
        if not edge and coarse >= params.half_stage_below:
            M = M_try
    if edge or coarse < params.half_stage_below:
        M, coarse, _ = _coarse_search(li, j_half, M, Q, size, params.search_px, params, angles)
    # fine: the overlap as the coarse match places it
    rect = overlap_rect(M, size, params.margin_px, params.min_overlap)
    if rect is None:
        return None
    x0, y0, x1, y1 = rect
    template = li.full.crop(x0, y0, x1, y1)
    if _std(template.image[::2, ::2]) < params.min_texture:
        return None
    W0 = (Q @ M @ np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1.0]]))[:2]  # template pixel -> turned-j pixel
    # Lucas-Kanade on the half- and then the full-resolution image: wide basin, then precision
    tw, th = x1 - x0, y1 - y0
    pad = 6 + int(params.max_refine_px + params.max_refine_rad * max(tw, th) / 2)
    full0 = W0
    if coarse < params.half_stage_below or len(angles) > 1:  # a weak or uncertain coarse match: widen the basin first
        half0 = _scale_warp(W0, 0.5)
        crop, cW = _crop_for(j_half, half0, tw // 2, th // 2, pad)
        hW, _, _, _ = refine_euclidean(li.half.crop(x0 // 2, y0 // 2, x1 // 2, y1 // 2), crop, _shift_origin(cW, x0 % 2 / 2, y0 % 2 / 2),
                                       points=params.points // 4, iterations=params.iterations)
        hW = _uncrop(_shift_origin(hW, -(x0 % 2) / 2, -(y0 % 2) / 2), cW, half0)
        full0 = _scale_warp(hW, 2.0)
    crop, cW = _crop_for(j_full, full0, tw, th, pad)
    W, score, mean_i, mean_j = refine_euclidean(template, crop, cW, points=params.points, iterations=params.iterations)
    W = _uncrop(W, cW, full0)
    if not np.isfinite(W).all() or score < params.min_score:
        return None
    centre = np.array([tw / 2, th / 2, 1.0])
    turned_by = abs(np.arctan2(W[1, 0], W[0, 0]) - np.arctan2(W0[1, 0], W0[0, 0]))
    if np.abs(W @ centre - W0 @ centre).max() > params.max_refine_px or turned_by > params.max_refine_rad:
        return None  # the refinement ran away from the coarse match
    M_ij = np.linalg.inv(Q) @ np.vstack([W, [0, 0, 1]]) @ np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1.0]])
    return delta_of_map(M_ij, size), score, mean_i, mean_j


def _coarse_search(li: Level, j_half: Gray, M: NDArray[np.float64], Q: NDArray[np.float64], size: tuple[int, int], search_px: int,
                   params: RegistrationParams, angles: Sequence[float]) -> tuple[NDArray[np.float64], float, bool]:
    """Normalised cross-correlation of frame i's overlap (shrunk by the search radius, so
    it stays inside frame j for any guess error up to it; the radius is halved until a
    template is left) over ±``search_px`` of frame j at half resolution, at the best of
    ``angles`` added to the guessed rotation (chosen at a quarter of the resolution when
    there are several). Returns the corrected i→j map, the peak correlation (0 when there
    is nothing to search) and whether the peak lies on the window's edge (the true match
    may be further)."""
    s, rect = search_px // 2 * 2, None
    while s >= 4:  # the widest search that leaves a template (small frames, narrow overlaps)
        rect = overlap_rect(M, size, params.margin_px + s, params.min_overlap / 2)
        if rect is not None:
            break
        s = s // 4 * 2
    if rect is None:
        return M, 0.0, False
    hx0, hy0, hx1, hy1 = (v // 2 for v in rect)
    template = li.half.image[hy0:hy1, hx0:hx1]
    if hx1 - hx0 <= 8 or hy1 - hy0 <= 8 or _std(template) < params.min_texture:
        return M, 0.0, False
    hs = s // 2
    centre = np.array([(rect[0] + rect[2]) / 2, (rect[1] + rect[3]) / 2])
    origin = np.array([[1, 0, 2 * (hx0 - hs)], [0, 1, 2 * (hy0 - hs)], [0, 0, 1.0]])  # the searched window, full-resolution px
    window = (hx1 - hx0 + 2 * hs, hy1 - hy0 + 2 * hs)

    def at_angle(angle: float, f: int = 2, j_img: Gray = j_half, tmpl: Gray = template) -> tuple[float, NDArray[np.float64], bool]:
        # the guess turned by ``angle`` about the overlap's centre, searched at 1/f resolution
        R = _rot(angle)
        Ma = M @ np.vstack([np.hstack([R, (centre - R @ centre)[:, None]]), [0, 0, 1]])
        size_f = (-(-window[0] * 2 // f), -(-window[1] * 2 // f))
        seen = cv2.warpAffine(j_img, _scale_warp((Q @ Ma @ origin)[:2], 1 / f), size_f, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        res = cv2.matchTemplate(seen, tmpl, cv2.TM_CCOEFF_NORMED)
        at = _parabola_peak(res)
        shift = f * at - 2 * hs
        edge = bool(min(at[0], at[1]) < 1 or at[0] > res.shape[1] - 2 or at[1] > res.shape[0] - 2)
        return float(res.max()), Ma @ np.array([[1, 0, shift[0]], [0, 1, shift[1]], [0, 0, 1.0]]), edge

    if len(angles) == 1:
        peak, M_best, edge = at_angle(angles[0])
        return M_best, peak, edge
    # several angles: climbed at a quarter of the resolution (4x cheaper) when the overlap
    # leaves a template there, then searched at half at the best one
    small = cv2.pyrDown(template)
    if min(small.shape) > 8:
        j_quarter = cv2.pyrDown(j_half)
        best = _climb(sorted(angles), lambda a: at_angle(a, 4, j_quarter, small)[0])
    else:
        best = _climb(sorted(angles), lambda a: at_angle(a)[0])
    peak, M_best, edge = at_angle(best)
    return M_best, peak, edge


def _climb(angles: Sequence[float], score: Callable[[float], float]) -> float:
    """The angle of ``angles`` (sorted) scoring best, found by climbing from the one nearest
    0 towards the rising score while it rises (the correlation is unimodal about the true
    turn): 3-4 angles scored for a small turn, whatever the range searched."""
    scores: dict[int, float] = {}

    def at(i: int) -> float:
        if i not in scores:
            scores[i] = score(angles[i])
        return scores[i]

    i = int(np.argmin(np.abs(angles)))
    sides = [i + d for d in (-1, 1) if 0 <= i + d < len(angles)]
    if sides and max(at(j) for j in sides) > at(i):
        step = max(sides, key=at) - i
        i += step
        while 0 <= i + step < len(angles) and at(i + step) > at(i):
            i += step
    return angles[i]


def _std(image: Gray) -> float:
    """Grey-level standard deviation (OpenCV's: NumPy's takes ~10x longer on a crop)."""
    return float(cv2.meanStdDev(image)[1][0, 0])


def _shift_origin(W: NDArray[np.float64], dx: float, dy: float) -> NDArray[np.float64]:
    """A warp for a template whose pixel (0, 0) sits at (dx, dy) of the original's."""
    return W[:2] @ np.array([[1, 0, dx], [0, 1, dy], [0, 0, 1.0]])


def _parabola_peak(res: NDArray[np.float32]) -> NDArray[np.float64]:
    """Sub-pixel (x, y) of a correlation surface's maximum (a parabola through the peak)."""
    _, _, _, (px, py) = cv2.minMaxLoc(res)
    fx, fy = float(px), float(py)
    if 0 < px < res.shape[1] - 1:
        a, b, c = res[py, px - 1], res[py, px], res[py, px + 1]
        fx += 0.5 * (a - c) / (a - 2 * b + c) if a - 2 * b + c != 0 else 0.0
    if 0 < py < res.shape[0] - 1:
        a, b, c = res[py - 1, px], res[py, px], res[py + 1, px]
        fy += 0.5 * (a - c) / (a - 2 * b + c) if a - 2 * b + c != 0 else 0.0
    return np.array([fx, fy])


def _scale_warp(W: NDArray[np.float64], f: float) -> NDArray[np.float64]:
    """The same Euclidean warp between images scaled by ``f`` (pyramid levels, pixel centres
    at integer coordinates as in ``cv2.pyrDown``)."""
    out = W.copy()
    out[:, 2] = W[:, 2] * f
    return out


def candidate_pairs(poses: NDArray[np.float64], size: tuple[int, int], *, skip_consecutive: bool = False) -> list[tuple[int, int]]:
    """Pairs (i < j) of frames whose centres are close enough for their footprints to overlap
    (the overlap itself is checked when the pair is registered)."""
    reach = 0.9 * max(size)
    out = []
    centres = poses[:, :2]
    order = np.argsort(centres[:, 0])
    xs = centres[order, 0]
    for a, i in enumerate(order):
        hi = np.searchsorted(xs, xs[a] + reach, side="right")
        for j in order[a + 1 : hi]:
            if np.linalg.norm(centres[j] - centres[i]) < reach:
                p = (int(min(i, j)), int(max(i, j)))
                if not (skip_consecutive and p[1] == p[0] + 1):
                    out.append(p)
    return sorted(out, key=lambda p: (p[1], p[0]))


def solve_pose_graph(
    initial: NDArray[np.float64], measurements: Sequence[PairMeasurement], priors: NDArray[np.float64] | None, params: RegistrationParams = RegistrationParams(),
    *, iterations: int = 10,
) -> NDArray[np.float64]:
    """Poses (N, 3) minimising the robust pose-graph error (Gauss-Newton with Huber weights).

    Each measurement says where frame j is in frame i's frame; ``priors`` (N-1, 3), the
    odometry's relative steps, weakly hold frames that no image measurement reaches.
    Frame 0 stays where ``initial`` puts it (the gauge).
    """
    n = len(initial)
    edges = [(m.i, m.j, m.delta, 1.0) for m in measurements]
    if priors is not None:
        edges += [(k, k + 1, priors[k], params.prior_weight) for k in range(n - 1)]
    if n < 2 or not edges:
        return initial.copy()
    I = np.array([e[0] for e in edges])
    J = np.array([e[1] for e in edges])
    Z = np.array([e[2] for e in edges], float)
    base_w = np.array([e[3] for e in edges], float)
    x = initial.astype(np.float64).copy()
    L = params.lever_px
    for _ in range(iterations):
        ti, tj, th = x[I, :2], x[J, :2], x[I, 2]
        c, s = np.cos(th), np.sin(th)
        d = tj - ti
        pred = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
        r = np.column_stack([pred - Z[:, :2], L * wrap_angle(x[J, 2] - th - Z[:, 2])])
        norm = np.linalg.norm(r, axis=1)
        w = base_w * np.where(norm <= params.huber_px, 1.0, params.huber_px / np.maximum(norm, 1e-12))
        # Jacobian: rows 3e..3e+2 of edge e, columns of pose i and pose j
        ne = len(edges)
        one = np.ones(ne)
        blocks = [  # (residual row, node, pose component, derivative)
            (0, I, 0, -c), (0, I, 1, -s), (0, I, 2, -s * d[:, 0] + c * d[:, 1]),
            (1, I, 0, s), (1, I, 1, -c), (1, I, 2, -c * d[:, 0] - s * d[:, 1]),
            (2, I, 2, -L * one), (0, J, 0, c), (0, J, 1, s), (1, J, 0, -s), (1, J, 1, c), (2, J, 2, L * one),
        ]
        e = np.arange(ne)
        rows = np.concatenate([3 * e + r for r, _, _, _ in blocks])
        cols = np.concatenate([3 * node + k for _, node, k, _ in blocks])
        vals = np.concatenate([v for _, _, _, v in blocks])
        Jm = sp.csr_matrix((vals, (rows, cols)), shape=(3 * ne, 3 * n))
        Wd = sp.diags(np.repeat(w, 3))
        H = (Jm.T @ Wd @ Jm).tocsc()[3:, 3:]  # frame 0 fixed
        g = (Jm.T @ (np.repeat(w, 3) * r.ravel()))[3:]
        H = H + sp.identity(H.shape[0], format="csc") * 1e-9
        step = spsolve(H, -g)
        x[1:] += step.reshape(n - 1, 3)
        x[:, 2] = wrap_angle(x[:, 2])
        if np.abs(step).max() < 1e-4:
            break
    return x


def measurement_residuals(poses: NDArray[np.float64], measurements: Sequence[PairMeasurement], params: RegistrationParams) -> NDArray[np.float64]:
    """Size (px) of each measurement's disagreement with the poses."""
    out = []
    for m in measurements:
        r = relative_pose(poses[m.i], poses[m.j]) - m.delta
        out.append(float(np.hypot(r[0], r[1]) + params.lever_px * abs(float(wrap_angle(r[2])))))
    return np.array(out)


def solve_gains(n: int, measurements: Sequence[PairMeasurement], *, sigma_n: float = 0.5, sigma_g: float = 0.1) -> NDArray[np.float64]:
    """Per-frame exposure gains that make overlapping frames equally bright (Brown & Lowe's
    gain compensation: min Σ (g_i m_i − g_j m_j)² / σ_n² + Σ (g_k − 1)² / σ_g², with m the
    mean grey of the same surface points in both frames; Brown & Lowe sum the first term
    over every overlapping pixel, here one term per pair carries that weight by a small
    σ_n, so the prior only fixes the overall level)."""
    A = sp.lil_matrix((n, n))
    b = np.full(n, 1.0 / sigma_g**2)
    for k in range(n):
        A[k, k] = 1.0 / sigma_g**2
    for m in measurements:
        a, c = m.mean_i, m.mean_j
        A[m.i, m.i] += a * a / sigma_n**2
        A[m.j, m.j] += c * c / sigma_n**2
        A[m.i, m.j] -= a * c / sigma_n**2
        A[m.j, m.i] -= a * c / sigma_n**2
    return np.asarray(spsolve(A.tocsc(), b), dtype=np.float64)


CONSECUTIVE_RUN = 8  # consecutive pairs registered by one thread in a row


def _runs(count: int, workers: int) -> list[range]:
    """0..count split into runs of about :data:`CONSECUTIVE_RUN`, as many per worker."""
    pieces = max(1, workers) * max(1, -(-count // (max(1, workers) * CONSECUTIVE_RUN)))
    edges = [round(count * k / pieces) for k in range(pieces + 1)]
    return [range(a, b) for a, b in pairwise(edges) if b > a]


def _nearest_measured(measurements: Sequence[PairMeasurement | None], k: int, count: int = 2) -> list[int]:
    """Indices of the ``count`` measured entries nearest to entry k (the one before first
    when two are as near)."""
    found: list[int] = []
    for step in range(1, len(measurements)):  # outwards from k: no scan of a whole long session per pair
        for j in (k - step, k + step):
            if 0 <= j < len(measurements) and measurements[j] is not None:
                found.append(j)
                if len(found) == count:
                    return found
    return found


def chain(first: NDArray[np.float64], deltas: Sequence[NDArray[np.float64]]) -> NDArray[np.float64]:
    """Poses from a first pose and the relative step to each next frame."""
    out = [np.asarray(first, float)]
    for d in deltas:
        out.append(compose_pose(out[-1], d))
    return np.array(out)


BLIND_ANGLES = tuple(np.radians([-8.0, -6.0, -4.0, -2.0, 0.0, 2.0, 4.0, 6.0, 8.0]))  # turns searched when there is no odometry (climbed from 0)
SURE_MATCH = 0.9  # a verified guess this good ends the search (true matches ≥ 0.98, false ones ≤ 0.88, measured)


def estimate_poses(
    load: Callable[[int], Level], n: int, guess: NDArray[np.float64] | None, params: RegistrationParams = RegistrationParams(),
    progress: Callable[[float, str], None] | None = None,
) -> PoseEstimate:
    """Globally consistent frame poses from images (and an odometry guess when given).

    1. initial steps: odometry, or phase correlation between consecutive frames;
    2. every consecutive pair registered (sub-pixel), the steps chained;
    3. every other overlapping pair (lane neighbours, revisits) registered from the chain;
    4. the pose graph solved robustly; pairs that still disagree by more than
       ``max_residual_px`` are dropped and the graph solved again.
    Frames that no accepted pair reaches keep their odometry placement and are flagged.
    ``load(k)`` gives frame k's grey levels; it is called from ``params.workers`` threads.
    """
    report = progress or (lambda f, m: None)
    if n == 0:
        raise ValueError("no frames")
    h, w = load(0).shape
    size = (w, h)
    with ThreadPoolExecutor(max(1, params.workers)) as pool:

        # an image-only guess can be tens of pixels off: search wider, let the refinement travel
        blind_params = replace(params, search_px=2 * params.search_px, max_refine_px=3 * params.search_px)

        def measure(pair: tuple[int, int], start: NDArray[np.float64], angles: Sequence[float] = (0.0,)) -> PairMeasurement | None:
            found = register_pair(load(pair[0]), load(pair[1]), start, params if len(angles) == 1 else blind_params, angles=angles)
            if found is None:
                return None
            delta, score, mi, mj = found
            return PairMeasurement(pair[0], pair[1], delta, score, mi, mj)

        views: dict[tuple[int, int], PhaseView] = {}  # frames prepared for phase correlation, until their pairs are done

        def phase_view(k: int, scale: int) -> PhaseView:
            view = views.get((k, scale))
            if view is None:
                view = views[k, scale] = PhaseView.of(load(k).half.image, scale, reduced=2)
            return view

        def blind_guesses(k: int, previous: PairMeasurement | None) -> Iterator[NDArray[np.float64]]:
            # phase correlation at a quarter of the resolution; then the step of the pair
            # before (a robot moves much as it did a frame earlier); then at half resolution
            for n_scale, scale in enumerate(PHASE_SCALES):
                if n_scale == 1 and previous is not None:
                    yield previous.delta
                for g, _ in phase_candidates(phase_view(k, scale), phase_view(k + 1, scale)):
                    yield g

        def measure_blind(k: int, next_too: bool = False, previous: PairMeasurement | None = None,
                          ) -> tuple[PairMeasurement | None, NDArray[np.float64]]:
            # without odometry: guesses verified by registration until one verifies surely;
            # frame k+1's preparations are kept when the same thread measures pair k+1 next
            tried: list[PairMeasurement] = []
            first_guess = None
            for g in blind_guesses(k, previous):
                first_guess = g if first_guess is None else first_guess
                m = measure((k, k + 1), g, BLIND_ANGLES)
                if m is not None:
                    tried.append(m)
                    if m.score > SURE_MATCH:
                        break
            for scale in PHASE_SCALES:
                views.pop((k, scale), None)
                if not next_too:
                    views.pop((k + 1, scale), None)
            if tried:
                best = max(tried, key=lambda m: m.score)
                return best, best.delta
            return None, first_guess if first_guess is not None else np.zeros(3)

        def measure_blind_run(ks: range) -> list[tuple[PairMeasurement | None, NDArray[np.float64]]]:
            out: list[tuple[PairMeasurement | None, NDArray[np.float64]]] = []
            for k in ks:
                out.append(measure_blind(k, k + 1 in ks, out[-1][0] if out else None))
            return out

        report(0.05, "registering consecutive frames")
        # each thread takes runs of consecutive pairs: the threads then prepare different
        # frames instead of waiting in turn for the frame the other one is decoding
        runs = _runs(n - 1, params.workers)
        if guess is None:
            blind = [r for run in pool.map(measure_blind_run, runs) for r in run]
            consecutive = [m for m, _ in blind]
            steps = [step for _, step in blind]
            # a pair no phase-correlation guess could place (its overlap's texture drowned by
            # something else): a robot moves much as it did a frame earlier or later, so the
            # nearest placed pairs' steps are tried as guesses (and kept as its prior)
            for k in [k for k, m in enumerate(consecutive) if m is None]:
                near = _nearest_measured(consecutive, k)
                for j in near:
                    found = measure((k, k + 1), consecutive[j].delta, BLIND_ANGLES)  # type: ignore[union-attr]
                    if found is not None:
                        consecutive[k] = found
                        break
                if near:
                    steps[k] = consecutive[k].delta if consecutive[k] is not None else consecutive[near[0]].delta  # type: ignore[union-attr]
            priors = np.array(steps).reshape(-1, 3)
            guess = chain(np.zeros(3), list(priors))
        else:
            guess = np.asarray(guess, dtype=np.float64)
            priors = np.array([relative_pose(guess[k], guess[k + 1]) for k in range(n - 1)]).reshape(-1, 3)
            consecutive = [m for run in pool.map(lambda ks: [measure((k, k + 1), priors[k]) for k in ks], runs) for m in run]
            # where the odometry was too far off (wheel slip), the images alone decide
            lost = [k for k, m in enumerate(consecutive) if m is None]
            for k, (m, _) in zip(lost, pool.map(measure_blind, lost)):
                consecutive[k] = m
        steps_now = [m.delta if m is not None else priors[k] for k, m in enumerate(consecutive)]
        chained = chain(guess[0], steps_now)
        report(0.4, "registering overlapping frames")
        others = candidate_pairs(chained, size, skip_consecutive=True)
        # the chain is accurate where consecutive pairs registered: search near it, then wider
        near = replace(params, search_px=max(8, params.search_px // 3))

        def measure_other(p: tuple[int, int]) -> PairMeasurement | None:
            start = relative_pose(chained[p[0]], chained[p[1]])
            found = register_pair(load(p[0]), load(p[1]), start, near)
            if found is None:
                return measure(p, start)
            delta, score, mi, mj = found
            return PairMeasurement(p[0], p[1], delta, score, mi, mj)

        found = list(pool.map(measure_other, others))
    measurements = [m for m in consecutive + found if m is not None]
    report(0.8, "solving the pose graph")
    poses = solve_pose_graph(chained, measurements, priors, params)
    res = measurement_residuals(poses, measurements, params)
    keep = [m for m, r in zip(measurements, res) if r <= params.max_residual_px]
    rejected = len(measurements) - len(keep)
    if rejected:
        poses = solve_pose_graph(poses, keep, priors, params)
    confident = np.zeros(n, bool)
    confident[0] = n == 1
    for m in keep:
        confident[[m.i, m.j]] = True
    return PoseEstimate(poses, confident, keep, rejected)
