"""Registration of one pair of overlapping frames: where frame j lies in frame i's frame.

A coarse normalised cross-correlation (at half resolution, over quarter turns and a few
angles) followed by sub-pixel Lucas–Kanade with rotation (:mod:`processing.stitching.lucas_kanade`).
Relative poses are (dx, dy, dθ) in frame i's centred pixel coordinates
(:func:`processing.poses.relative_se2`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.poses import delta_of_map, frame_i_to_j, rot2, wrap_angle
from processing.stitching.lucas_kanade import Smoothed, refine_euclidean
from processing.stitching.phase import Gray, quarter_turned
from processing.stitching.warps import crop_for, scale_warp, shift_origin, uncrop


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
    # refine at half resolution first when the coarse correlation is weaker
    half_stage_below: float = 0.9
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


def _quarter_turn(k: int, size: tuple[int, int]) -> NDArray[np.float64]:
    """3x3 pixel map of ``cv2.rotate`` by k quarter turns clockwise on screen, for (w, h)."""
    w, h = size
    return [
        np.eye(3),
        np.array([[0, -1, h - 1], [1, 0, 0], [0, 0, 1.0]]),
        np.array([[-1, 0, w - 1], [0, -1, h - 1], [0, 0, 1.0]]),
        np.array([[0, 1, 0], [-1, 0, w - 1], [0, 0, 1.0]]),
    ][k]


def overlap_rect(
    M: NDArray[np.float64], size: tuple[int, int], margin: int, min_overlap: float
) -> tuple[int, int, int, int] | None:
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


FIRST_SEARCH_PX = 12  # the coarse search's first radius (full-resolution pixels)
# pairs guessed to overlap less than this share of ``min_overlap`` are not searched
EARLY_OVERLAP = 0.9
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
        return cls(Smoothed.of(gray, SIGMA), Smoothed.of(cast(Gray, cv2.pyrDown(gray)), SIGMA))

    @property
    def shape(self) -> tuple[int, int]:
        """(h, w) at full resolution."""
        return self.full.image.shape

    @property
    def nbytes(self) -> int:
        """Memory it holds."""
        return self.full.image.nbytes + self.half.image.nbytes


def register_pair(
    frame_i: Level | Gray,
    frame_j: Level | Gray,
    guess: NDArray[np.floating],
    params: RegistrationParams = RegistrationParams(),
    *,
    angles: Sequence[float] = (0.0,),
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
    j_full = quarter_turned(lj.full.image, k)
    j_half = quarter_turned(lj.half.image, k)
    Q = _quarter_turn(k, size)
    M, coarse = _coarse_match(li, j_half, M, Q, size, params, angles)
    # fine: the overlap as the coarse match places it
    rect = overlap_rect(M, size, params.margin_px, params.min_overlap)
    if rect is None:
        return None
    x0, y0, x1, y1 = rect
    template = li.full.crop(x0, y0, x1, y1)
    if _std(template.image[::2, ::2]) < params.min_texture:
        return None
    # template pixel -> turned-j pixel
    W0 = (Q @ M @ np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1.0]]))[:2]
    # a weak or uncertain coarse match: widen the basin first
    wide = coarse < params.half_stage_below or len(angles) > 1
    W, score, mean_i, mean_j = _fine_stage(li, template, j_full, j_half, W0, rect, wide, params)
    if not np.isfinite(W).all() or score < params.min_score:
        return None
    if _ran_away(W, W0, x1 - x0, y1 - y0, params):
        return None  # the refinement ran away from the coarse match
    M_ij = (
        np.linalg.inv(Q)
        @ np.vstack([W, [0, 0, 1]])
        @ np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1.0]])
    )
    return delta_of_map(M_ij, size), score, mean_i, mean_j


def _fine_stage(
    li: Level,
    template: Smoothed,
    j_full: Gray,
    j_half: Gray,
    W0: NDArray[np.float64],
    rect: tuple[int, int, int, int],
    wide: bool,
    params: RegistrationParams,
) -> tuple[NDArray[np.float64], float, float, float]:
    """Lucas-Kanade of frame i's overlap ``template`` (at ``rect``) on the turned frame j
    from the coarse warp ``W0`` (template pixel -> turned-j pixel): on the half-resolution
    image first where ``wide`` (a wide basin), then on the full-resolution one (precision).
    The refined warp, its score and the two frames' mean levels over the overlap."""
    x0, y0, x1, y1 = rect
    tw, th = x1 - x0, y1 - y0
    pad = 6 + int(params.max_refine_px + params.max_refine_rad * max(tw, th) / 2)
    full0 = _half_stage(li, j_half, W0, rect, pad, params) if wide else W0
    crop, cW = crop_for(j_full, full0, tw, th, pad)
    W, score, mean_i, mean_j = refine_euclidean(
        template, crop, cW, points=params.points, iterations=params.iterations
    )
    return uncrop(W, cW, full0), score, mean_i, mean_j


def _ran_away(
    W: NDArray[np.float64], W0: NDArray[np.float64], tw: int, th: int, params: RegistrationParams
) -> bool:
    """Whether the refined warp ``W`` moved the (``tw`` x ``th``) template's centre or turned
    it further from the coarse warp ``W0`` than ``params`` allow."""
    centre = np.array([tw / 2, th / 2, 1.0])
    turned_by = abs(np.arctan2(W[1, 0], W[0, 0]) - np.arctan2(W0[1, 0], W0[0, 0]))
    return bool(
        np.abs(W @ centre - W0 @ centre).max() > params.max_refine_px
        or turned_by > params.max_refine_rad
    )


def _coarse_match(
    li: Level,
    j_half: Gray,
    M: NDArray[np.float64],
    Q: NDArray[np.float64],
    size: tuple[int, int],
    params: RegistrationParams,
    angles: Sequence[float],
) -> tuple[NDArray[np.float64], float]:
    """The coarse match: a small search first (the guess is usually good); the full radius
    when its peak is weak or on the search window's edge. The map it places j by, and its
    score."""
    coarse, edge = 0.0, True
    if len(angles) == 1 and params.search_px > FIRST_SEARCH_PX:
        M_try, coarse, edge = _coarse_search(
            li, j_half, M, Q, size, FIRST_SEARCH_PX, params, angles
        )
        if not edge and coarse >= params.half_stage_below:
            M = M_try
    if edge or coarse < params.half_stage_below:
        M, coarse, _ = _coarse_search(li, j_half, M, Q, size, params.search_px, params, angles)
    return M, coarse


def _half_stage(
    li: Level,
    j_half: Gray,
    W0: NDArray[np.float64],
    rect: tuple[int, int, int, int],
    pad: int,
    params: RegistrationParams,
) -> NDArray[np.float64]:
    """Lucas-Kanade at half resolution from the coarse warp ``W0`` (template pixel ->
    turned-j pixel, full resolution): the full-resolution warp to start from."""
    x0, y0, x1, y1 = rect
    tw, th = x1 - x0, y1 - y0
    half0 = scale_warp(W0, 0.5)
    crop, cW = crop_for(j_half, half0, tw // 2, th // 2, pad)
    hW, _, _, _ = refine_euclidean(
        li.half.crop(x0 // 2, y0 // 2, x1 // 2, y1 // 2),
        crop,
        shift_origin(cW, x0 % 2 / 2, y0 % 2 / 2),
        points=params.points // 4,
        iterations=params.iterations,
    )
    hW = uncrop(shift_origin(hW, -(x0 % 2) / 2, -(y0 % 2) / 2), cW, half0)
    return scale_warp(hW, 2.0)


def _search_window(
    M: NDArray[np.float64], size: tuple[int, int], search_px: int, params: RegistrationParams
) -> tuple[int, tuple[int, int, int, int]] | None:
    """The widest search radius (even, up to ``search_px``, halved while none is left)
    that leaves a template of frame i's overlap, and that template's rectangle; None for
    small frames or narrow overlaps where no radius does."""
    s = search_px // 2 * 2
    while s >= 4:
        rect = overlap_rect(M, size, params.margin_px + s, params.min_overlap / 2)
        if rect is not None:
            return s, rect
        s = s // 4 * 2
    return None


def _coarse_search(
    li: Level,
    j_half: Gray,
    M: NDArray[np.float64],
    Q: NDArray[np.float64],
    size: tuple[int, int],
    search_px: int,
    params: RegistrationParams,
    angles: Sequence[float],
) -> tuple[NDArray[np.float64], float, bool]:
    """Normalised cross-correlation of frame i's overlap (shrunk by the search radius, so
    it stays inside frame j for any guess error up to it; the radius is halved until a
    template is left) over ±``search_px`` of frame j at half resolution, at the best of
    ``angles`` added to the guessed rotation (chosen at a quarter of the resolution when
    there are several). Returns the corrected i→j map, the peak correlation (0 when there
    is nothing to search) and whether the peak lies on the window's edge (the true match
    may be further)."""
    found = _search_window(M, size, search_px, params)
    if found is None:
        return M, 0.0, False
    s, rect = found
    hx0, hy0, hx1, hy1 = (v // 2 for v in rect)
    template = li.half.image[hy0:hy1, hx0:hx1]
    if hx1 - hx0 <= 8 or hy1 - hy0 <= 8 or _std(template) < params.min_texture:
        return M, 0.0, False
    hs = s // 2
    centre = np.array([(rect[0] + rect[2]) / 2, (rect[1] + rect[3]) / 2])
    # the searched window, full-resolution px
    origin = np.array([[1, 0, 2 * (hx0 - hs)], [0, 1, 2 * (hy0 - hs)], [0, 0, 1.0]])
    window = (hx1 - hx0 + 2 * hs, hy1 - hy0 + 2 * hs)

    def at_angle(
        angle: float, f: int = 2, j_img: Gray = j_half, tmpl: Gray = template
    ) -> tuple[float, NDArray[np.float64], bool]:
        # the guess turned by ``angle`` about the overlap's centre, searched at 1/f resolution
        R = rot2(angle)
        Ma = M @ np.vstack([np.hstack([R, (centre - R @ centre)[:, None]]), [0, 0, 1]])
        peak, shift, edge = _correlate(j_img, tmpl, Q @ Ma @ origin, window, f, hs)
        return peak, Ma @ np.array([[1, 0, shift[0]], [0, 1, shift[1]], [0, 0, 1.0]]), edge

    if len(angles) == 1:
        peak, M_best, edge = at_angle(angles[0])
        return M_best, peak, edge
    # several angles: climbed at a quarter of the resolution (4x cheaper) when the overlap
    # leaves a template there, then searched at half at the best one
    small = cast(Gray, cv2.pyrDown(template))
    if min(small.shape) > 8:
        j_quarter = cast(Gray, cv2.pyrDown(j_half))
        best = _climb(sorted(angles), lambda a: at_angle(a, 4, j_quarter, small)[0])
    else:
        best = _climb(sorted(angles), lambda a: at_angle(a)[0])
    peak, M_best, edge = at_angle(best)
    return M_best, peak, edge


def _correlate(
    j_img: Gray,
    tmpl: Gray,
    A: NDArray[np.float64],
    window: tuple[int, int],
    f: int,
    hs: int,
) -> tuple[float, NDArray[np.float64], bool]:
    """Normalised cross-correlation of ``tmpl`` over the ``window`` (half-resolution px,
    searched ±``hs``) of the turned frame j (``j_img``, at 1/``f`` resolution) that warp
    ``A`` (window pixel -> turned-j pixel, full resolution) samples. The peak correlation,
    the shift of the window it gives (full-resolution px, sub-pixel; 0 where the guess is)
    and whether the peak lies on the window's edge."""
    size_f = (-(-window[0] * 2 // f), -(-window[1] * 2 // f))
    seen = cv2.warpAffine(
        j_img,
        scale_warp(A[:2], 1 / f),
        size_f,
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
    )
    res = cast(NDArray[np.float32], cv2.matchTemplate(seen, tmpl, cv2.TM_CCOEFF_NORMED))
    at = _parabola_peak(res)
    shift = f * at - 2 * hs
    edge = bool(min(at[0], at[1]) < 1 or at[0] > res.shape[1] - 2 or at[1] > res.shape[0] - 2)
    return float(res.max()), shift, edge


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
