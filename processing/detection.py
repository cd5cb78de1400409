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
import numba
import numpy as np
from numpy.typing import NDArray
from skimage.filters import threshold_sauvola

from processing.defects import Components
from processing.labels import component_flags, lookup
from processing.peaks import dominant_peaks, smooth_histogram, valley_emphasis_threshold
from processing.region_growing import grow_regions
from processing.ridges import line_emphasis

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
    if method == "paper":
        return paper_cracks(gray)
    if method != "proposed":
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return proposed_cracks(gray, params)


def tile_cores(shape: tuple[int, int], tile_px: int, overlap_px: int) -> list[tuple[slice, slice, slice, slice]]:
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
            out.append((slice(y0, y1), slice(x0, x1), slice(y - y0, cy1 - y0), slice(x - x0, cx1 - x0)))
    return out


def _core(rows: slice, cols: slice, core_rows: slice, core_cols: slice) -> tuple[slice, slice]:
    """A tile core's slices in image coordinates."""
    return (slice(rows.start + core_rows.start, rows.start + core_rows.stop),
            slice(cols.start + core_cols.start, cols.start + core_cols.stop))


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
    R = line_emphasis(gray, sigma1=params.sigma1, scale_factor=params.scale_factor, n_scales=params.n_scales, mu=params.mu)
    if float(R.max()) <= 0 or not dark.any():
        return np.zeros(gray.shape, bool)
    r8 = np.round(255 * R / R.max()).astype(np.uint8)
    t_r, _ = cv2.threshold(r8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    candidates = dark & (r8 > t_r)
    if not candidates.any():
        return candidates
    t_star = valley_emphasis_threshold(hist)
    g_defect = defect_peak if defect_peak is not None else float(gray[candidates].mean())
    grown = grow_regions(gray, candidates, max(abs(t_star - g_defect), 1.0), max_iter=params.grow_iterations)
    return remove_small(grown, params.min_area_px)


def select_components(labels: NDArray[np.int32], stats: NDArray[np.int32], keep: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Mask of the components whose ``keep`` flag is set (``labels`` and ``stats`` from
    ``cv2.connectedComponentsWithStats``, label 0 never kept).

    A lookup ``keep[labels]`` costs ~3 ns per pixel of the whole image; when the kept (or
    the dropped) components are few, painting them inside their boxes costs far less.
    """
    keep = keep.copy()
    keep[0] = False
    areas = stats[:, cv2.CC_STAT_WIDTH].astype(np.int64) * stats[:, cv2.CC_STAT_HEIGHT]
    kept, dropped = np.flatnonzero(keep), np.flatnonzero(~keep[1:]) + 1
    lookup_cost = 3.0 * labels.size
    paint_kept = 1.5 * areas[kept].sum() + 3000.0 * len(kept)
    paint_dropped = 1.5 * areas[dropped].sum() + 3000.0 * len(dropped) + 0.5 * labels.size
    if min(paint_kept, paint_dropped) >= lookup_cost:
        return lookup(labels, keep)
    if paint_kept <= paint_dropped:
        out = np.zeros(labels.shape, bool)
        ids, value = kept, True
    else:
        out = labels > 0
        ids, value = dropped, False
    for i in ids.tolist():
        x, y, w, h = (int(v) for v in stats[i, :4])
        box = out[y : y + h, x : x + w]
        box[labels[y : y + h, x : x + w] == i] = value
    return out


def seeded_regions(candidates: NDArray[np.bool_], seeds: NDArray[np.bool_], *, min_area_px: int = 0,
                   max_half_width_px: float | None = None) -> NDArray[np.bool_]:
    """Region growing from seeds: the 8-connected regions of ``candidates`` that hold a
    seed pixel (and at least ``min_area_px`` pixels, and no inscribed radius over
    ``max_half_width_px`` when given: wider than a crack)."""
    grown = (candidates | seeds).astype(np.uint8)
    n, labels = cv2.connectedComponents(grown, connectivity=8)
    dist = None
    if max_half_width_px is not None:
        # components are separated by background, so each one's distance to the
        # background is its own: one transform serves all
        dist = cv2.distanceTransform(np.pad(grown, 1), cv2.DIST_L2, 3)[1:-1, 1:-1]
    area, seeded, thick = component_flags(labels, n, seeds, dist, max_half_width_px or np.inf)
    keep = seeded & (area >= min_area_px) & ~thick
    keep[0] = False
    return lookup(labels, keep)


def hysteresis(response: NDArray[np.floating], low: float, high: float, *, min_area_px: int = 0) -> NDArray[np.bool_]:
    """Hysteresis thresholding: regions above ``low`` that hold a pixel above ``high``."""
    return seeded_regions(response > low, response > high, min_area_px=min_area_px)


def sauvola_threshold(gray: NDArray[np.uint8], window: int, k: float, r: float = 127.5) -> NDArray[np.float32]:
    """Sauvola's local threshold m·(1 + k·(s/r − 1)) from box-filtered moments (as scikit-image)."""
    mean, sq = _local_moments(gray, window)
    var = cv2.max(cv2.subtract(sq, cv2.multiply(mean, mean)), 0.0)
    factor = cv2.sqrt(var)
    cv2.addWeighted(factor, k / r, factor, 0.0, 1.0 - k, dst=factor)  # 1 + k (s/r - 1)
    return cv2.multiply(mean, factor)


def below_sauvola(gray: NDArray[np.uint8], window: int, k: float, r: float = 127.5) -> NDArray[np.bool_]:
    """``gray < sauvola_threshold(gray, window, k, r)`` in one compiled pass after the box filters."""
    mean, sq = _local_moments(gray, window)
    out = np.empty(gray.shape, np.bool_)
    _below_sauvola(gray, mean, sq, np.float32(k), np.float32(r), out)
    return out


def _local_moments(gray: NDArray[np.uint8], window: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Mean and mean square over a ``window``-wide square (reflected borders)."""
    size = (window | 1, window | 1)
    mean = cv2.boxFilter(gray, cv2.CV_32F, size, borderType=cv2.BORDER_REFLECT)
    sq = cv2.sqrBoxFilter(gray, cv2.CV_32F, size, borderType=cv2.BORDER_REFLECT)
    return mean, sq


@numba.njit(nogil=True, cache=True)
def _below_sauvola(gray: NDArray[np.uint8], mean: NDArray[np.float32], sq: NDArray[np.float32], k: np.float32, r: np.float32,
                   out: NDArray[np.bool_]) -> None:  # pragma: no cover - compiled
    rows, cols = gray.shape
    for y in range(rows):
        for x in range(cols):
            m = mean[y, x]
            var = max(sq[y, x] - m * m, np.float32(0))
            out[y, x] = gray[y, x] < m * (1 + k * (np.sqrt(var) / r - 1))


def drop_along(mask: NDArray[np.bool_], lines: NDArray[np.bool_], *, band_px: int = 4, max_fraction: float = 0.5) -> NDArray[np.bool_]:
    """Drop components lying mostly within ``band_px`` of ``lines`` (e.g. mosaic seams)."""
    if not mask.any() or not lines.any():
        return mask
    comps = Components.of(mask)
    return select_components(comps.labels, comps.stats, _off_lines(comps, lines, band_px=band_px, max_fraction=max_fraction))


def _off_lines(comps: Components, lines: NDArray[np.bool_], *, band_px: int = 4, max_fraction: float = 0.5) -> NDArray[np.bool_]:
    """Per component: not lying mostly (> ``max_fraction``) within ``band_px`` of ``lines``."""
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band_px + 1,) * 2)
    near = cv2.dilate(lines.astype(np.uint8), k)
    near &= (comps.labels > 0).view(np.uint8)
    on = np.bincount(comps.labels[near > 0], minlength=len(comps.keep))
    keep = on <= max_fraction * np.maximum(comps.stats[:, cv2.CC_STAT_AREA], 1)
    keep[0] = False
    return keep


def remove_small(mask: NDArray[np.bool_], min_area_px: int) -> NDArray[np.bool_]:
    """Drop connected components smaller than ``min_area_px`` pixels."""
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    area, _, _ = component_flags(labels, n)
    keep = area >= min_area_px
    keep[0] = False
    return lookup(labels, keep)


def estimate_background(gray: NDArray[np.uint8], background_px: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Lightly smoothed image and its background (a grey closing, which erases dark thin
    structures), both float32."""
    k = max(3, background_px | 1)
    smooth = cv2.GaussianBlur(gray, (3, 3), 0)
    # a square element: OpenCV separates it into two 1-D passes (an ellipse costs ~10x more)
    background = cv2.morphologyEx(smooth, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    return smooth.astype(np.float32), background.astype(np.float32)


def proposed_cracks(gray: NDArray[np.uint8], params: CrackParams = CrackParams()) -> NDArray[np.bool_]:
    """The improved pipeline: illumination normalisation, scale-normalised Hessian line
    emphasis (eq. 14 with σ_i²), then region growing from strong line seeds (the paper's
    enhanced segmentation) over pixels that are line-like or locally dark (Sauvola), small
    components removed, and only the crack's own dark pixels kept."""
    return _proposed(gray, params)[0]


def _proposed(gray: NDArray[np.uint8], params: CrackParams) -> tuple[NDArray[np.bool_], NDArray[np.float32]]:
    """``proposed_cracks`` and each pixel's darkness below its background (grey levels)."""
    smooth, background = estimate_background(gray, params.background_px)
    contrast = cv2.subtract(background, smooth)
    norm = cv2.divide(smooth, cv2.max(background, 1.0))
    R = line_emphasis(norm, sigma1=params.sigma1, scale_factor=params.scale_factor, n_scales=params.n_scales,
                      mu=params.mu, normalise=True, half_resolution_from=params.half_resolution_from)
    if float(R.max()) < params.high:
        return np.zeros(gray.shape, bool), contrast
    dark = below_sauvola(gray, params.local_window_px, params.local_k)
    # a seed must be darker than its surroundings by a few grey levels, not only in ratio:
    # in near-black areas sensor noise alone makes large ratios
    seeds = (R > params.high) & (contrast > params.min_contrast_levels)
    # shadows and plate edges are wider than cracks
    mask = seeded_regions(dark | (R > params.low), seeds, min_area_px=params.min_area_px,
                          max_half_width_px=params.max_half_width_px)
    if params.min_darkness > 0:  # keep the crack's own dark pixels, not its blurred halo
        mask &= norm < 1.0 - params.min_darkness
        mask = remove_small(mask, params.min_area_px // 4)
    return mask, contrast


def corrosion_candidates(image: NDArray[np.uint8], params: CorrosionParams = CorrosionParams()) -> NDArray[np.bool_]:
    """Rust-coloured pixels of a BGR image (hue and saturation), cleaned by an opening and
    a closing; components of any size."""
    hsv = cv2.cvtColor(cv2.GaussianBlur(image, (5, 5), 0), cv2.COLOR_BGR2HSV)
    mask = cv2.inRange(hsv, (params.hue_min, params.min_saturation, 0), (params.hue_max, 255, 255))
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8)) > 0


def detect_corrosion(image: NDArray[np.generic], *, params: CorrosionParams = CorrosionParams()) -> NDArray[np.bool_]:
    """Boolean (H, W) mask of rust-coloured areas (needs a BGR image; gray gives none)."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        return np.zeros(image.shape[:2], bool)
    return remove_small(corrosion_candidates(image, params), params.min_area_px)


def _quarter(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """An image at a quarter of its resolution (area average)."""
    for _ in range(2):  # two halvings: OpenCV's 2x area path is ~15x faster than one 4x
        h, w = image.shape[:2]
        image = cv2.resize(image, (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_AREA)
    return image


def _covered_quarter(coverage: NDArray[np.generic]) -> NDArray[np.bool_]:
    """4x4 blocks fully inside the covered area (``coverage`` > 0)."""
    covered = cv2.threshold(coverage.astype(np.uint8, copy=False), 0, 255, cv2.THRESH_BINARY)[1]
    return _quarter(covered) == 255


def _surface_background_quarter(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """The grey surface brightness with dark details closed away (a 45-px disk), at a
    quarter of the resolution: it varies slowly."""
    small = _quarter(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image)
    return cv2.morphologyEx(small, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (11, 11)))


def surface_level(image: NDArray[np.uint8], coverage: NDArray[np.generic]) -> float:
    """The surface's typical brightness: median of the grey background over covered pixels."""
    covered = _covered_quarter(coverage)
    return float(np.median(_surface_background_quarter(image)[covered])) if covered.any() else 0.0


def on_surface(image: NDArray[np.uint8], coverage: NDArray[np.generic], level: float | None = None) -> NDArray[np.bool_]:
    """Where a mosaic shows the steel surface: not far darker than the surface typically
    is (``level``; beyond a plate's edge the camera sees the dark void below), and well
    inside the covered area (its edge is a dark step, not a crack); decided on 4x4 blocks."""
    background = _surface_background_quarter(image)
    covered = _covered_quarter(coverage)
    if level is None:
        level = float(np.median(background[covered])) if covered.any() else 0.0
    surface = ((background > 0.4 * level) & covered).astype(np.uint8)
    surface = cv2.erode(surface, np.ones((7, 7), np.uint8))  # ~15 px on each side
    h, w = image.shape[:2]
    full = np.zeros((h, w), np.uint8)
    up = cv2.resize(surface, (surface.shape[1] * 4, surface.shape[0] * 4), interpolation=cv2.INTER_NEAREST)
    full[: up.shape[0], : up.shape[1]] = up[:h, :w]
    return full > 0
