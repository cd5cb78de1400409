"""Mosaic of downward-camera frames in world coordinates (paper §3.1).

This is the first version: frames are placed by the camera motion (odometry, or phase
correlation when there is none) and each placement is refined by appearance-based
template matching against the previous frame, as the paper describes. Global pose
optimisation and the exposure blending of eq. (2) build on it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.alignment import align_frames


@dataclass(frozen=True)
class StitchParams:
    """Options of the stitcher."""

    search_px: int = 24
    min_score: float = 0.5
    min_overlap: float = 0.15
    flat_field_min_frames: int = 8
    global_alignment: bool = True


@dataclass
class Mosaic:
    """A stitched mosaic and where every frame went.

    ``frame_poses_px`` is (N, 3): frame-centre x, y in mosaic pixels and rotation in degrees.
    Mosaic pixel (u, v) is at world ``origin_m + (u, v) / px_per_m``.
    """

    image: NDArray[np.uint8]
    coverage: NDArray[np.bool_]
    px_per_m: float
    origin_m: tuple[float, float]
    frame_poses_px: NDArray[np.float64]
    confident: NDArray[np.bool_]
    seams: NDArray[np.bool_] | None = None  # where a later frame's border cuts an earlier one

    def to_world(self, u: float, v: float) -> tuple[float, float]:
        """World (x, y) in metres of a mosaic pixel."""
        return self.origin_m[0] + u / self.px_per_m, self.origin_m[1] + v / self.px_per_m


@dataclass(frozen=True)
class _Patch:
    image: NDArray[np.uint8]
    mask: NDArray[np.uint8]
    x0: int
    y0: int


def _warp_to_world(frame: NDArray[np.uint8], cx: float, cy: float, theta: float) -> _Patch:
    """Rotate a frame by ``theta`` (rad) about its centre placed at mosaic pixel (cx, cy)."""
    h, w = frame.shape[:2]
    c, s = np.cos(theta), np.sin(theta)
    R = np.array([[c, -s], [s, c]])
    half = np.array([(w - 1) / 2, (h - 1) / 2])
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]]) - half
    pts = corners @ R.T + (cx, cy)
    x0, y0 = np.floor(pts.min(axis=0)).astype(int)
    x1, y1 = np.ceil(pts.max(axis=0)).astype(int)
    M = np.hstack([R, (np.array([cx - x0, cy - y0]) - R @ half)[:, None]])
    size = (int(x1 - x0 + 1), int(y1 - y0 + 1))
    img = cv2.warpAffine(frame, M, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    mask = cv2.warpAffine(np.full((h, w), 255, np.uint8), M, size, flags=cv2.INTER_NEAREST)
    mask = cv2.erode(mask, np.ones((3, 3), np.uint8))
    return _Patch(img, mask, int(x0), int(y0))


def _gray(img: NDArray[np.uint8]) -> NDArray[np.uint8]:
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img


def match_offset(
    prev: _Patch, new: _Patch, search_px: int, min_overlap: float
) -> tuple[float, float, float] | None:
    """Translation (dx, dy) to add to ``new`` so it matches ``prev``, and the match score.

    Template matching (normalised cross-correlation) of the part of ``new`` that the
    placement says overlaps ``prev``, searched within ``search_px``; sub-pixel by a
    parabola through the peak. None when the overlap is too small to match.
    """
    ax0, ay0 = max(prev.x0, new.x0), max(prev.y0, new.y0)
    ax1 = min(prev.x0 + prev.mask.shape[1], new.x0 + new.mask.shape[1])
    ay1 = min(prev.y0 + prev.mask.shape[0], new.y0 + new.mask.shape[0])
    tx0, ty0, tx1, ty1 = ax0 + search_px, ay0 + search_px, ax1 - search_px, ay1 - search_px
    area_new = new.mask.shape[0] * new.mask.shape[1]
    if tx1 - tx0 < 16 or ty1 - ty0 < 16 or (tx1 - tx0) * (ty1 - ty0) < min_overlap * area_new * 0.5:
        return None
    tmpl = _gray(new.image)[ty0 - new.y0 : ty1 - new.y0, tx0 - new.x0 : tx1 - new.x0]
    tmask = new.mask[ty0 - new.y0 : ty1 - new.y0, tx0 - new.x0 : tx1 - new.x0]
    sx0, sy0 = max(tx0 - search_px, prev.x0), max(ty0 - search_px, prev.y0)
    sx1 = min(tx1 + search_px, prev.x0 + prev.mask.shape[1])
    sy1 = min(ty1 + search_px, prev.y0 + prev.mask.shape[0])
    search = _gray(prev.image)[sy0 - prev.y0 : sy1 - prev.y0, sx0 - prev.x0 : sx1 - prev.x0]
    if search.shape[0] <= tmpl.shape[0] or search.shape[1] <= tmpl.shape[1] or tmask.min() == 0:
        return None
    if float(tmpl.std()) < 1.0:
        return None  # no texture to match
    res = cv2.matchTemplate(search, tmpl, cv2.TM_CCOEFF_NORMED)
    _, score, _, (px, py) = cv2.minMaxLoc(res)
    fx, fy = float(px), float(py)
    if 0 < px < res.shape[1] - 1:
        l, c, r = res[py, px - 1], res[py, px], res[py, px + 1]
        den = l - 2 * c + r
        fx += 0.5 * (l - r) / den if den != 0 else 0.0
    if 0 < py < res.shape[0] - 1:
        u, c, d = res[py - 1, px], res[py, px], res[py + 1, px]
        den = u - 2 * c + d
        fy += 0.5 * (u - d) / den if den != 0 else 0.0
    return sx0 + fx - tx0, sy0 + fy - ty0, float(score)


def estimate_flat_field(frames: Sequence[NDArray[np.uint8]]) -> NDArray[np.float32]:
    """Relative brightness of each pixel position over many frames (vignetting), (H, W).

    The per-pixel median of the frames, each divided by its own mean, smoothed; dividing
    a frame by it evens out its corners so seams between frames do not show.
    """
    stack = np.stack([_gray(f).astype(np.float32) / max(float(_gray(f).mean()), 1.0) for f in frames])
    field = np.median(stack, axis=0)
    h, w = field.shape
    field = cv2.GaussianBlur(field, (0, 0), max(h, w) / 20)
    return (field / max(float(field.mean()), 1e-6)).astype(np.float32)


def apply_flat_field(frame: NDArray[np.uint8], field: NDArray[np.float32]) -> NDArray[np.uint8]:
    """Divide a frame by its flat field."""
    f = field if frame.ndim == 2 else field[..., None]
    return np.clip(frame.astype(np.float32) / np.maximum(f, 0.2) + 0.5, 0, 255).astype(np.uint8)


def estimate_motion_phase(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> tuple[float, float]:
    """Image-only translation of frame ``b`` relative to ``a`` by phase correlation (px).

    Phase correlation is ambiguous modulo the image size (a 190 px shift of a 320 px
    frame reads as -130 px); each wrap-around candidate is scored by the normalised
    correlation of the overlap it implies, and the best one is returned.
    """
    ga, gb = (_gray(x).astype(np.float32) for x in (a, b))
    h, w = ga.shape
    win = cv2.createHanningWindow((w, h), cv2.CV_32F)
    (px, py), _ = cv2.phaseCorrelate(ga, gb, win)
    best, best_score = (-px, -py), -np.inf
    for dx in (-px, -px - w, -px + w):
        for dy in (-py, -py - h, -py + h):
            ix, iy = int(round(dx)), int(round(dy))
            ow, oh = w - abs(ix), h - abs(iy)
            if ow < 8 or oh < 8 or ow * oh < 0.05 * w * h:
                continue
            pa = ga[max(iy, 0) : max(iy, 0) + oh, max(ix, 0) : max(ix, 0) + ow]
            pb = gb[max(-iy, 0) : max(-iy, 0) + oh, max(-ix, 0) : max(-ix, 0) + ow]
            score = float(cv2.matchTemplate(pa, pb, cv2.TM_CCOEFF_NORMED)[0, 0])
            if score > best_score:
                best, best_score = (dx, dy), score
    return best


def stitch_frames(
    frames: Sequence[NDArray[np.uint8]],
    poses: NDArray[np.floating] | None,
    *,
    px_per_m: float = 1.0,
    params: StitchParams = StitchParams(),
) -> Mosaic:
    """Stitch frames into one mosaic in world orientation.

    Parameters
    ----------
    frames : sequence of (H, W) or (H, W, 3) uint8 arrays, all the same size.
    poses : (N, 3) array of camera-centre x, y (metres) and yaw (radians) in the world,
        the initial guess; None to estimate motion from the images alone.
    px_per_m : image scale (pixels per metre on the surface).

    Returns
    -------
    Mosaic
    """
    if len(frames) == 0:
        raise ValueError("frames must not be empty")
    shape = frames[0].shape
    for i, f in enumerate(frames):
        if f.shape != shape or f.dtype != np.uint8:
            raise ValueError(f"frame {i} is {f.dtype} {f.shape}; all frames must be uint8 {shape}")
    if px_per_m <= 0:
        raise ValueError(f"px_per_m must be positive, got {px_per_m}")
    if len(frames) >= params.flat_field_min_frames:
        field = estimate_flat_field(frames)
        frames = [apply_flat_field(f, field) for f in frames]
    if poses is None:
        guess = np.zeros((len(frames), 3))
        for i in range(1, len(frames)):
            dx, dy = estimate_motion_phase(frames[i - 1], frames[i])
            guess[i] = guess[i - 1] + (dx, dy, 0.0)
    else:
        poses = np.asarray(poses, dtype=np.float64)
        if poses.shape != (len(frames), 3):
            raise ValueError(f"poses must be ({len(frames)}, 3), got {poses.shape}")
        guess = np.column_stack([poses[:, :2] * px_per_m, poses[:, 2]])
    placed = guess.copy()
    confident = np.zeros(len(frames), bool)
    confident[0] = True
    patches = [_warp_to_world(frames[0], placed[0, 0], placed[0, 1], placed[0, 2])]
    for i in range(1, len(frames)):
        # carry the correction found so far (odometry drift is cumulative)
        placed[i, :2] = placed[i - 1, :2] + (guess[i, :2] - guess[i - 1, :2])
        placed[i, 2] = guess[i, 2]
        patch = _warp_to_world(frames[i], placed[i, 0], placed[i, 1], placed[i, 2])
        found = match_offset(patches[i - 1], patch, params.search_px, params.min_overlap)
        if found is not None and found[2] >= params.min_score:
            placed[i, :2] += found[:2]
            confident[i] = True
            patch = _warp_to_world(frames[i], placed[i, 0], placed[i, 1], placed[i, 2])
        else:
            placed[i, :2] = guess[i, :2] + (placed[i - 1, :2] - guess[i - 1, :2])
        patches.append(patch)
    if params.global_alignment and len(frames) > 1:
        placed, _, linked = align_frames(frames, placed)
        confident = linked
        patches = [_warp_to_world(f, *p) for f, p in zip(frames, placed)]
    return _compose(patches, placed, confident, px_per_m, shape)


def _compose(
    patches: list[_Patch],
    placed: NDArray[np.float64],
    confident: NDArray[np.bool_],
    px_per_m: float,
    shape: tuple[int, ...],
) -> Mosaic:
    x0 = min(p.x0 for p in patches)
    y0 = min(p.y0 for p in patches)
    x1 = max(p.x0 + p.mask.shape[1] for p in patches)
    y1 = max(p.y0 + p.mask.shape[0] for p in patches)
    canvas = np.zeros((y1 - y0, x1 - x0) + tuple(shape[2:]), np.uint8)
    coverage = np.zeros((y1 - y0, x1 - x0), bool)
    owner = np.zeros((y1 - y0, x1 - x0), np.float32)
    for i, p in enumerate(patches, 1):
        ys, xs = slice(p.y0 - y0, p.y0 - y0 + p.mask.shape[0]), slice(p.x0 - x0, p.x0 - x0 + p.mask.shape[1])
        m = p.mask > 0
        image = p.image
        seen = coverage[ys, xs] & m
        if seen.sum() > 1000:  # exposure compensation: match the new frame's gain to the mosaic
            gain = float(np.median(canvas[ys, xs][seen])) / max(float(np.median(image[seen])), 1.0)
            image = np.clip(image.astype(np.float32) * np.clip(gain, 0.6, 1.6) + 0.5, 0, 255).astype(np.uint8)
        # the newest frame wins where frames overlap: no blending, so no ghosting of thin
        # cracks where two frames disagree by a pixel or two
        canvas[ys, xs][m] = image[m]
        coverage[ys, xs] |= m
        owner[ys, xs][m] = i
    # seams: where the frame that supplies the pixels changes
    k = np.ones((3, 3), np.uint8)
    seams = ((cv2.dilate(owner, k) != owner) | (cv2.erode(owner, k) != owner)) & coverage
    seams &= cv2.erode(coverage.astype(np.uint8), k) > 0
    poses_px = np.column_stack([placed[:, 0] - x0, placed[:, 1] - y0, np.degrees(placed[:, 2])])
    origin = (x0 / px_per_m, y0 / px_per_m)
    return Mosaic(canvas, coverage, px_per_m, origin, poses_px, confident, seams)
