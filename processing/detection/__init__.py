"""Crack and corrosion detection and the measurement of each defect (paper §3.3).

Methods: ``paper`` (the published pipeline: automatic peak detection, Hessian line
emphasis, region growing), ``proposed`` (illumination-normalised, scale-normalised line
emphasis with thresholds in units of the image's own texture), ``learned`` (the shipped
crack network, :mod:`processing.detection.learned`), and the paper's baselines ``otsu`` and
``sauvola``; rust areas by colour; each defect measured as an object.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import partial
from typing import Any, Literal, cast

import cv2
import numpy as np
from numpy.typing import NDArray
from skimage.filters import threshold_sauvola

from processing.detection.confidence import Calibration
from processing.detection.corrosion import CorrosionParams, corrosion_candidates, rust_saturation
from processing.detection.crack_filter import (
    CrackParams,
    SurfaceStats,
    estimate_background,
    proposed_cracks,
    proposed_with_contrast,
    sample_surface,
)
from processing.detection.defects import Components, Defect, measure_defects
from processing.detection.learned import (
    LearnedParams,
    crack_probability,
    crack_threshold,
    learned_cracks,
    load_model,
)
from processing.detection.peaks import dominant_peaks, smooth_histogram, valley_emphasis_threshold
from processing.detection.region_growing import grow_regions
from processing.detection.ridges import line_emphasis
from processing.detection.thresholds import (
    remove_small,
    select_components,
)
from processing.detection.tiling import tile_core, tile_cores

Method = Literal["proposed", "learned", "paper", "otsu", "sauvola"]
METHODS: tuple[str, ...] = ("proposed", "learned", "paper", "otsu", "sauvola")
CrackMethod = Literal["proposed", "learned"]
SAUVOLA_WINDOW, SAUVOLA_K = 25, 0.2  # the paper's Sauvola baseline


@dataclass(frozen=True)
class PaperParams:
    """Parameters of the published pipeline (paper §3.3)."""

    sigma1: float = 1.0
    scale_factor: float = 2**0.5
    n_scales: int = 3
    mu: float = 0.5
    min_area_px: int = 30
    grow_iterations: int = 50


def to_gray(image: NDArray[np.generic]) -> NDArray[np.uint8]:
    """8-bit grayscale of an 8/16-bit gray or BGR(A) image; raise ValueError otherwise."""
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(
            image,  # type: ignore[arg-type]  # any dtype: OpenCV refuses those it cannot convert
            cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY,
        )
    if image.ndim != 2:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {image.shape}")
    if image.dtype == np.uint16:
        image = (cast(NDArray[np.uint16], image) / 257.0).round().astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"image must be uint8 or uint16, got {image.dtype}")
    return cast(NDArray[np.uint8], image)  # its dtype checked above


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
        t = threshold_sauvola(gray, window_size=SAUVOLA_WINDOW, k=SAUVOLA_K)
        return gray < t
    if method == "paper":
        return paper_cracks(gray)
    if method == "learned":
        return learned_cracks(gray)
    if method != "proposed":
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return proposed_cracks(gray, params)


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
    if len(tiles) == 1 or method == "learned":  # the network tiles by itself
        return detect_cracks(image, method=method)
    out = np.zeros(image.shape[:2], bool)
    gray = to_gray(image)
    surface = sample_surface(gray, window_px=tile_px) if method == "proposed" else None

    def run(tile: tuple[slice, slice, slice, slice]) -> None:
        rows, cols, cr, cc = tile
        part = gray[rows, cols]
        mask = (
            proposed_cracks(part, surface=surface)
            if surface is not None
            else detect_cracks(part, method=method)
        )
        out[tile_core(*tile)] = mask[cr, cc]

    _each(run, tiles, workers)
    return out


def _each(fn: Callable[[Any], None], items: Sequence[Any], workers: int) -> None:
    """``fn`` on every item, on up to ``workers`` threads (here, without a pool, for one)."""
    if workers <= 1 or len(items) <= 1:
        for item in items:
            fn(item)
        return
    with ThreadPoolExecutor(max_workers=min(workers, len(items))) as pool:
        list(pool.map(fn, items))


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
    probability: NDArray[np.float32] | None = None  # the network's (``learned`` only)
    calibration: Calibration | None = None  # its per-defect confidence, when it has one


def defect_masks(
    image: NDArray[np.uint8],
    valid: NDArray[np.bool_] | None = None,
    seams: NDArray[np.bool_] | None = None,
    *,
    crack_method: CrackMethod = "proposed",
    surface: SurfaceStats | None = None,
    crack_params: CrackParams = CrackParams(),
    corrosion_params: CorrosionParams = CorrosionParams(),
    tile_px: int = 1024,
    overlap_px: int = 64,
    workers: int = 2,
    learned_params: LearnedParams = LearnedParams(),
) -> DefectMasks:
    """Crack (``crack_method``, the network's settings in ``learned_params``) and rust masks
    of a BGR image of any size, tile by tile on ``workers`` threads; only ``valid`` pixels
    count; components lying along ``seams`` (exposure steps where mosaic frames meet:
    straight dark edges) are not cracks, nor
    are cracks on a rust patch's rim (counted as corrosion). ``proposed`` measures its
    thresholds in ``surface`` (sampled from the image when not given), the same in every
    tile."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"image must be (H, W, 3) uint8 BGR, got {image.shape} {image.dtype}")
    shape = image.shape[:2]
    cracks = np.zeros(shape, bool)
    rust = np.zeros(shape, bool)
    contrast = np.zeros(shape, np.float32)

    def run(tile: tuple[slice, slice, slice, slice]) -> None:
        rows, cols, cr, cc = tile
        part = image[rows, cols]
        core = tile_core(*tile)
        gray = cast(NDArray[np.uint8], cv2.cvtColor(part, cv2.COLOR_BGR2GRAY))
        if min(gray.shape) >= 3 and learned is not None:
            smooth, background = estimate_background(
                gray, crack_params.background_px, crack_params.light_sigma
            )
            cracks[core] = learned[core]
            contrast[core] = cv2.subtract(background, smooth)[cr, cc]
        elif min(gray.shape) >= 3:
            mask, dark_by = proposed_with_contrast(gray, crack_params, surface)
            cracks[core], contrast[core] = mask[cr, cc], dark_by[cr, cc]
        rust[core] = corrosion_candidates(part, corrosion_params, rust_sat)[cr, cc]

    # the network runs once over the image (its own tiles, all cores to each)
    probability, learned, calibration = None, None, None
    if crack_method == "learned" and min(shape) >= 3:
        model = load_model(learned_params.model_path, learned_params.threads)
        probability = crack_probability(to_gray(image), learned_params)
        learned = probability > crack_threshold(learned_params)
        calibration = Calibration.from_record(model.record)
    tiles = tile_cores(shape, tile_px, overlap_px)
    if surface is None and crack_method == "proposed" and len(tiles) > 1:
        surface = sample_surface(image, crack_params, tile_px)
    rust_sat = (
        surface.rust_saturation
        if surface is not None and surface.rust_saturation is not None
        else rust_saturation(image, corrosion_params)
    )
    _each(run, tiles, workers)
    kept = _kept(cracks, rust, contrast, valid, seams, corrosion_params)
    return replace(kept, probability=probability, calibration=calibration)


def _kept(
    cracks: NDArray[np.bool_],
    rust: NDArray[np.bool_],
    contrast: NDArray[np.float32],
    valid: NDArray[np.bool_] | None,
    seams: NDArray[np.bool_] | None,
    corrosion_params: CorrosionParams,
) -> DefectMasks:
    """The candidates that count: on ``valid`` pixels, rust patches large enough, cracks
    neither on a rust patch's rim nor lying along ``seams``; with their components."""
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
    near = cast(NDArray[np.uint8], cv2.dilate(lines.astype(np.uint8), k))
    near &= (comps.labels > 0).view(np.uint8)
    on = np.bincount(comps.labels[near > 0], minlength=len(comps.keep))
    keep = on <= max_fraction * np.maximum(comps.stats[:, cv2.CC_STAT_AREA], 1)
    keep[0] = False
    return keep


def find_defects(
    image: NDArray[np.uint8],
    mm_per_px: float | None,
    valid: NDArray[np.bool_] | None = None,
    seams: NDArray[np.bool_] | None = None,
    workers: int = 2,
    method: CrackMethod = "proposed",
    surface: SurfaceStats | None = None,
    network_threads: int = 2,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], list[Defect]]:
    """Crack (by ``method``) and rust masks of one (H, W, 3) uint8 BGR image, and its
    defects measured (``mm_per_px``: the image's scale, None for pixels only); rust and
    cracks are measured on two threads when ``workers`` allows."""
    masks = defect_masks(
        image,
        valid,
        seams,
        crack_method=method,
        surface=surface,
        workers=workers,
        learned_params=LearnedParams(threads=network_threads),
    )
    cracks = partial(
        measure_defects,
        masks.cracks,
        "crack",
        mm_per_px=mm_per_px,
        contrast=masks.contrast,
        components=masks.crack_components,
        probability=masks.probability,
        calibration=masks.calibration,
    )
    rust = partial(
        measure_defects,
        masks.rust,
        "corrosion",
        mm_per_px=mm_per_px,
        components=masks.rust_components,
    )
    if workers <= 1:
        found, rusty = cracks(), rust()
    else:
        with ThreadPoolExecutor(max_workers=2) as pool:  # labelling and distances release the GIL
            other = pool.submit(rust)
            found, rusty = cracks(), other.result()
    found += [replace(d, id=len(found) + d.id) for d in rusty]
    return masks.cracks, masks.rust, found
