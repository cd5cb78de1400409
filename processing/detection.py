"""Crack and corrosion detection and the measurement of each defect (paper §3.3).

Methods: ``paper`` (the published pipeline: automatic peak detection, Hessian line
emphasis, region growing), ``proposed`` (illumination-normalised, scale-normalised line
emphasis with hysteresis region growing), and the paper's baselines ``otsu`` and
``sauvola``; rust areas by colour; each defect measured as an object.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from skimage.filters import threshold_sauvola

from processing.defects import Components
from processing.peaks import dominant_peaks, smooth_histogram, valley_emphasis_threshold
from processing.region_growing import grow_regions
from processing.ridges import line_emphasis
from processing.thresholds import (
    below_sauvola,
    remove_small,
    seeded_regions,
    select_components,
)

Method = Literal["proposed", "paper", "otsu", "sauvola"]
METHODS: tuple[str, ...] = ("proposed", "paper", "otsu", "sauvola")


@dataclass(frozen=True)
class PaperParams:
    """Parameters of the published pipeline (paper §3.3)."""

    sigma1: float = 1.0
    scale_factor: float = 2**0.5
    n_scales: int = 3
    mu: float = 0.5
    min_area_px: int = 30
    grow_iterations: int = 50


@dataclass(frozen=True)
class CrackParams:
    """Options of the ``proposed`` crack detector (sizes in pixels).

    Tuned on the DeepCrack development split (two-fold cross-validation when tuned:
    0.871 / 0.867); with the fused filter and σ ≥ 1.4 at half resolution, pooled
    2-px-tolerant DSC 0.868 / 0.868 on its even and odd images, where the best Sauvola
    setting with small-object removal scores 0.858 / 0.858.
    """

    background_px: int = 45
    sigma1: float = 1.0
    scale_factor: float = 2**0.5
    n_scales: int = 6
    mu: float = 0.5
    high: float = 0.12
    low: float = 0.1
    half_resolution_from: float | None = 1.4
    min_contrast_levels: float = 6.0
    max_half_width_px: float = 35.0
    local_window_px: int = 61
    local_k: float = 0.4
    min_area_px: int = 300
    min_darkness: float = 0.1
    sauvola_window: int = 25
    sauvola_k: float = 0.2


@dataclass(frozen=True)
class CorrosionParams:
    """Options of the rust detector."""

    hue_min: int = 0
    hue_max: int = 22
    min_saturation: int = 90
    min_area_px: int = 400


def to_gray(image: NDArray[np.generic]) -> NDArray[np.uint8]:
    """8-bit grayscale of an 8/16-bit gray or BGR(A) image; raise ValueError otherwise."""
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(
            image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        )
    if image.ndim != 2:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {image.shape}")
    if image.dtype == np.uint16:
        image = (image / 257.0).round().astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"image must be uint8 or uint16, got {image.dtype}")
    return image


def detect_cracks(
    image: NDArray[np.generic], *, method: Method = "proposed", params: CrackParams = CrackParams()
) -> NDArray[np.bool_]:
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
    if method == "paper":
        return paper_cracks(gray)
    if method != "proposed":
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return proposed_cracks(gray, params)


def tile_cores(
    shape: tuple[int, int], tile_px: int, overlap_px: int
) -> list[tuple[slice, slice, slice, slice]]:
    """Tiles covering an (H, W) image: for each, the tile's (rows, cols) slices with
    ``overlap_px`` of context and, relative to the tile, the slices of its core; the
    cores partition the image."""
    if tile_px <= 2 * overlap_px:
        raise ValueError(f"tile_px ({tile_px}) must exceed twice overlap_px ({overlap_px})")
    h, w = shape
    if h <= tile_px and w <= tile_px:
        return [(slice(0, h), slice(0, w), slice(0, h), slice(0, w))]
    step = tile_px - 2 * overlap_px
    out = []
    for y in range(0, h, step):
        for x in range(0, w, step):
            y0, x0 = max(0, y - overlap_px), max(0, x - overlap_px)
            y1, x1 = min(h, y + step + overlap_px), min(w, x + step + overlap_px)
            cy1, cx1 = min(h, y + step), min(w, x + step)
            out.append(
                (slice(y0, y1), slice(x0, x1), slice(y - y0, cy1 - y0), slice(x - x0, cx1 - x0))
            )
    return out


def _core(rows: slice, cols: slice, core_rows: slice, core_cols: slice) -> tuple[slice, slice]:
    """A tile core's slices in image coordinates."""
    return (
        slice(rows.start + core_rows.start, rows.start + core_rows.stop),
        slice(cols.start + core_cols.start, cols.start + core_cols.stop),
    )


def detect_cracks_tiled(
    image: NDArray[np.generic],
    *,
    method: Method = "proposed",
    tile_px: int = 1024,
    overlap_px: int = 64,
    workers: int = 2,
) -> NDArray[np.bool_]:
    """Crack mask of a large image (a mosaic) computed tile by tile on ``workers`` threads.

    Tiles overlap by ``overlap_px`` so filters see context across borders; each tile
    contributes only its core, so a crack crossing a border comes out as one region.
    """
    tiles = tile_cores(image.shape[:2], tile_px, overlap_px)
    if len(tiles) == 1:
        return detect_cracks(image, method=method)
    out = np.zeros(image.shape[:2], bool)

    def run(tile: tuple[slice, slice, slice, slice]) -> None:
        rows, cols, cr, cc = tile
        out[_core(*tile)] = detect_cracks(image[rows, cols], method=method)[cr, cc]

    with ThreadPoolExecutor(max_workers=workers) as pool:
        list(pool.map(run, tiles))
    return out


@dataclass(frozen=True)
class DefectMasks:
    """Per-pixel results of one image: crack and rust masks, how much darker than its
    surroundings each pixel is (grey levels; for crack widths at half contrast), and each
    mask's labelled components (for measuring without labelling again)."""

    cracks: NDArray[np.bool_]
    rust: NDArray[np.bool_]
    contrast: NDArray[np.float32]
    crack_components: Components
    rust_components: Components


def defect_masks(
    image: NDArray[np.uint8],
    valid: NDArray[np.bool_] | None = None,
    seams: NDArray[np.bool_] | None = None,
    *,
    crack_params: CrackParams = CrackParams(),
    corrosion_params: CorrosionParams = CorrosionParams(),
    tile_px: int = 1024,
    overlap_px: int = 64,
    workers: int = 2,
) -> DefectMasks:
    """Crack (``proposed``) and rust masks of a BGR image of any size, tile by tile on
    ``workers`` threads; only ``valid`` pixels count; components lying along ``seams``
    (exposure steps where mosaic frames meet: straight dark edges) are not cracks, nor
    are cracks on a rust patch's rim (counted as corrosion)."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"image must be (H, W, 3) uint8 BGR, got {image.shape} {image.dtype}")
    shape = image.shape[:2]
    cracks = np.zeros(shape, bool)
    rust = np.zeros(shape, bool)
    contrast = np.zeros(shape, np.float32)

    def run(tile: tuple[slice, slice, slice, slice]) -> None:
        rows, cols, cr, cc = tile
        part = image[rows, cols]
        core = _core(*tile)
        gray = cv2.cvtColor(part, cv2.COLOR_BGR2GRAY)
        if min(gray.shape) >= 3:
            mask, dark_by = _proposed(gray, crack_params)
            cracks[core], contrast[core] = mask[cr, cc], dark_by[cr, cc]
        rust[core] = corrosion_candidates(part, corrosion_params)[cr, cc]

    tiles = tile_cores(shape, tile_px, overlap_px)
    with ThreadPoolExecutor(max_workers=max(1, min(workers, len(tiles)))) as pool:
        list(pool.map(run, tiles))
    if valid is not None:
        rust &= valid
    rc = Components.of(rust)
    rc.keep[rc.stats[:, cv2.CC_STAT_AREA] < corrosion_params.min_area_px] = False
    rust = select_components(rc.labels, rc.stats, rc.keep)
    if valid is not None:
        cracks &= valid
    if rust.any():
        cracks &= cv2.dilate(rust.astype(np.uint8), np.ones((15, 15), np.uint8)) == 0
    cc = Components.of(cracks)
    if seams is not None and seams.any() and cracks.any():
        cc.keep[:] &= _off_lines(cc, seams)
        cracks = select_components(cc.labels, cc.stats, cc.keep)
    return DefectMasks(cracks, rust, contrast, cc, rc)


def global_threshold(hist: NDArray[np.floating]) -> tuple[int, int | None]:
    """Threshold from the dominant peaks: the valley between the background (highest)
    peak and the nearest darker dominant peak; valley-emphasis Otsu when there is none.

    Returns the threshold and the darker (defect) peak, or None for a unimodal histogram.
    """
    h = smooth_histogram(hist)
    peaks = dominant_peaks(hist).dominant
    background = int(peaks[np.argmax(h[peaks])])
    darker = peaks[peaks < background]
    if len(darker) == 0:
        return valley_emphasis_threshold(hist), None
    d = int(darker.max())
    return d + int(np.argmin(h[d : background + 1])), d


def paper_cracks(gray: NDArray[np.uint8], params: PaperParams = PaperParams()) -> NDArray[np.bool_]:
    """The published pipeline: peak-based global threshold ∧ Hessian line emphasis, then
    region growing with the valley-emphasis threshold, then small components removed."""
    hist = np.bincount(gray.ravel(), minlength=256).astype(np.float64)
    t_global, defect_peak = global_threshold(hist)
    dark = gray <= t_global
    R = line_emphasis(
        gray,
        sigma1=params.sigma1,
        scale_factor=params.scale_factor,
        n_scales=params.n_scales,
        mu=params.mu,
    )
    if float(R.max()) <= 0 or not dark.any():
        return np.zeros(gray.shape, bool)
    r8 = np.round(255 * R / R.max()).astype(np.uint8)
    t_r, _ = cv2.threshold(r8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    candidates = dark & (r8 > t_r)
    if not candidates.any():
        return candidates
    t_star = valley_emphasis_threshold(hist)
    g_defect = defect_peak if defect_peak is not None else float(gray[candidates].mean())
    grown = grow_regions(
        gray, candidates, max(abs(t_star - g_defect), 1.0), max_iter=params.grow_iterations
    )
    return remove_small(grown, params.min_area_px)


def _off_lines(
    comps: Components, lines: NDArray[np.bool_], *, band_px: int = 4, max_fraction: float = 0.5
) -> NDArray[np.bool_]:
    """Per component: not lying mostly (> ``max_fraction``) within ``band_px`` of ``lines``."""
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band_px + 1,) * 2)
    near = cv2.dilate(lines.astype(np.uint8), k)
    near &= (comps.labels > 0).view(np.uint8)
    on = np.bincount(comps.labels[near > 0], minlength=len(comps.keep))
    keep = on <= max_fraction * np.maximum(comps.stats[:, cv2.CC_STAT_AREA], 1)
    keep[0] = False
    return keep


def estimate_background(
    gray: NDArray[np.uint8], background_px: int
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Lightly smoothed image and its background (a grey closing, which erases dark thin
    structures), both float32."""
    k = max(3, background_px | 1)
    smooth = cv2.GaussianBlur(gray, (3, 3), 0)
    # a square element: OpenCV separates it into two 1-D passes (an ellipse costs ~10x more)
    background = cv2.morphologyEx(
        smooth, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    )
    return smooth.astype(np.float32), background.astype(np.float32)


def proposed_cracks(
    gray: NDArray[np.uint8], params: CrackParams = CrackParams()
) -> NDArray[np.bool_]:
    """The improved pipeline: illumination normalisation, scale-normalised Hessian line
    emphasis (eq. (14) with σ_i²), then region growing from strong line seeds (the paper's
    enhanced segmentation) over pixels that are line-like or locally dark (Sauvola), small
    components removed, and only the crack's own dark pixels kept."""
    return _proposed(gray, params)[0]


def _proposed(
    gray: NDArray[np.uint8], params: CrackParams
) -> tuple[NDArray[np.bool_], NDArray[np.float32]]:
    """``proposed_cracks`` and each pixel's darkness below its background (grey levels)."""
    smooth, background = estimate_background(gray, params.background_px)
    contrast = cv2.subtract(background, smooth)
    norm = cv2.divide(smooth, cv2.max(background, 1.0))
    R = line_emphasis(
        norm,
        sigma1=params.sigma1,
        scale_factor=params.scale_factor,
        n_scales=params.n_scales,
        mu=params.mu,
        normalise=True,
        half_resolution_from=params.half_resolution_from,
    )
    if float(R.max()) < params.high:
        return np.zeros(gray.shape, bool), contrast
    dark = below_sauvola(gray, params.local_window_px, params.local_k)
    # a seed must be darker than its surroundings by a few grey levels, not only in ratio:
    # in near-black areas sensor noise alone makes large ratios
    seeds = (R > params.high) & (contrast > params.min_contrast_levels)
    # shadows and plate edges are wider than cracks
    mask = seeded_regions(
        dark | (R > params.low),
        seeds,
        min_area_px=params.min_area_px,
        max_half_width_px=params.max_half_width_px,
    )
    if params.min_darkness > 0:  # keep the crack's own dark pixels, not its blurred halo
        mask &= norm < 1.0 - params.min_darkness
        mask = remove_small(mask, params.min_area_px // 4)
    return mask, contrast


def corrosion_candidates(
    image: NDArray[np.uint8], params: CorrosionParams = CorrosionParams()
) -> NDArray[np.bool_]:
    """Rust-coloured pixels of a BGR image (hue and saturation), cleaned by an opening and
    a closing; components of any size."""
    hsv = cv2.cvtColor(cv2.GaussianBlur(image, (5, 5), 0), cv2.COLOR_BGR2HSV)
    mask = cv2.inRange(hsv, (params.hue_min, params.min_saturation, 0), (params.hue_max, 255, 255))
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8)) > 0


def detect_corrosion(
    image: NDArray[np.generic], *, params: CorrosionParams = CorrosionParams()
) -> NDArray[np.bool_]:
    """Boolean (H, W) mask of rust-coloured areas (needs a BGR image; gray gives none)."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        return np.zeros(image.shape[:2], bool)
    return remove_small(corrosion_candidates(image, params), params.min_area_px)
