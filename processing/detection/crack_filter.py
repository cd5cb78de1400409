"""The ``proposed`` crack detector: illumination normalised, a scale-normalised
multi-scale line filter (eq. (14) with σ_i²), and thresholds measured in the surface's
own spread of line response and brightness (:class:`SurfaceStats`)."""

from __future__ import annotations

from dataclasses import astuple, dataclass, replace
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.detection.corrosion import rust_saturation
from processing.detection.ridges import line_emphasis
from processing.detection.thresholds import select_components


@dataclass(frozen=True)
class CrackParams:
    """Options of the ``proposed`` crack detector.

    Nothing here is a crack width, an image size or a grey level: the line filter's scales
    span hairlines to wide cracks (σ from ``sigma1`` in steps of ``scale_factor``), and the
    thresholds are in units of the image's own spread (median absolute deviation) of the
    line response and of the darkness, so textured and noisy surfaces raise them and clean
    ones lower them. A component is kept when it is elongated (length² / area ≥
    ``elongation``) and significant: its mean response, in spreads, times the square root
    of its length, at least ``significance`` (a long faint crack passes, a short faint
    speck does not).

    Chosen by leave-one-dataset-out over five public crack sets (pavement, concrete,
    masonry, ceramic tiles, drone imagery of concrete) for the largest worst-case ratio to
    the paper's Sauvola baseline; docs/benchmarks.md has the per-set scores.
    """

    sigma1: float = 0.8
    scale_factor: float = 2**0.5
    n_scales: int = 6
    mu: float = 0.5
    half_resolution_from: float | None = 2.0
    light_sigma: float = 0.6
    grow_spreads: float = 2.5
    dark_spreads: float = 2.0
    significance: float = 20.0
    elongation: float = 6.0

    @property
    def background_px(self) -> int:
        """Side of the closing that removes the widest crack the filter looks for."""
        sigma_max = self.sigma1 * self.scale_factor ** (self.n_scales - 1)
        return int(2 * np.ceil(3 * sigma_max) + 1)


def estimate_background(
    gray: NDArray[np.uint8], background_px: int, light_sigma: float = 0.6
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Lightly smoothed image and its background (a grey closing, which erases dark thin
    structures, then smoothed), both float32."""
    k = max(3, background_px | 1)
    smooth = cast(
        NDArray[np.float32], cv2.GaussianBlur(gray.astype(np.float32), (0, 0), light_sigma)
    )
    # a square element: OpenCV separates it into two 1-D passes (an ellipse costs ~10x more)
    background = cv2.morphologyEx(
        smooth, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    )
    return smooth, cast(NDArray[np.float32], cv2.GaussianBlur(background, (0, 0), k / 4))


@dataclass(frozen=True)
class SurfaceStats:
    """The surface's own statistics that the ``proposed`` thresholds are measured in: the
    median and spread (1.4826 · median absolute deviation) of the line response and of the
    normalised brightness; and the saturation above which a rust-hued pixel is rust (colour
    images). Measured on each image, or once for a whole mosaic (from its frames, or a
    sample of it) so that every tile and band uses the same."""

    line_median: float
    line_spread: float
    light_median: float
    light_spread: float
    rust_saturation: float | None = None

    @classmethod
    def of(cls, line: NDArray[np.float32], light: NDArray[np.float32]) -> SurfaceStats:
        """Statistics of (H, W) line response and normalised brightness arrays."""
        lm, ls = _median_spread(line)
        bm, bs = _median_spread(light)
        return cls(lm, ls, bm, bs)

    @classmethod
    def pooled(cls, many: list[SurfaceStats]) -> SurfaceStats:
        """The median of each statistic over several images (a mosaic's frames)."""
        lm, ls, bm, bs = np.median([astuple(s)[:4] for s in many], axis=0).tolist()
        rust = [s.rust_saturation for s in many if s.rust_saturation is not None]
        return cls(lm, ls, bm, bs, rust_saturation=float(np.median(rust)) if rust else None)


def _median_spread(values: NDArray[np.float32]) -> tuple[float, float]:
    sample = values[:: max(1, values.shape[0] // 256), :: max(1, values.shape[1] // 256)]
    med = float(np.median(sample))
    return med, 1.4826 * float(np.median(np.abs(sample - med))) + 1e-6


def _line_and_light(
    gray: NDArray[np.uint8], params: CrackParams
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """Line response R (eq. (14), scale-normalised) of the illumination-normalised image,
    that image (brightness / background) and the darkness below background (grey levels)."""
    smooth, background = estimate_background(gray, params.background_px, params.light_sigma)
    floor = cv2.max(background, 1.0)  # type: ignore[call-overload]  # OpenCV's stubs lack the scalar form
    norm = cast(NDArray[np.float32], cv2.divide(smooth, floor))
    R = line_emphasis(
        norm,
        sigma1=params.sigma1,
        scale_factor=params.scale_factor,
        n_scales=params.n_scales,
        mu=params.mu,
        normalise=True,
        half_resolution_from=params.half_resolution_from,
    )
    return R, norm, cast(NDArray[np.float32], cv2.subtract(background, smooth))


def measure_surface(image: NDArray[np.uint8], params: CrackParams = CrackParams()) -> SurfaceStats:
    """The :class:`SurfaceStats` of an (H, W) grey or (H, W, 3) BGR uint8 image (the rust
    saturation only for colour)."""
    gray = (
        cast(NDArray[np.uint8], cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
        if image.ndim == 3
        else image
    )
    R, norm, _ = _line_and_light(gray, params)
    stats = SurfaceStats.of(R, norm)
    if image.ndim == 3:
        stats = replace(stats, rust_saturation=rust_saturation(image))
    return stats


def sample_surface(
    gray: NDArray[np.uint8], params: CrackParams = CrackParams(), window_px: int = 1024
) -> SurfaceStats:
    """The :class:`SurfaceStats` of a large grey or BGR image, pooled over up to nine
    windows spread over it (every tile of a tiled pass then uses the same)."""
    h, w = gray.shape[:2]
    if h <= window_px and w <= window_px:
        return measure_surface(gray, params)
    ys = np.linspace(0, max(h - window_px, 0), 3).astype(int)
    xs = np.linspace(0, max(w - window_px, 0), 3).astype(int)
    windows = [gray[y : y + window_px, x : x + window_px] for y in ys for x in xs]
    found = [measure_surface(win, params) for win in windows if win.std() > 0]
    return SurfaceStats.pooled(found) if found else measure_surface(windows[0], params)


def proposed_cracks(
    gray: NDArray[np.uint8],
    params: CrackParams = CrackParams(),
    surface: SurfaceStats | None = None,
) -> NDArray[np.bool_]:
    """The improved pipeline: illumination normalised (image / background), scale-
    normalised multi-scale Hessian line emphasis (eq. (14) with σ_i²), line response and
    darkness each in units of the surface's own spread (``surface``, measured on the image
    when not given), then the connected regions of line-like dark pixels that are elongated
    and significant (see :class:`CrackParams`)."""
    return proposed_with_contrast(gray, params, surface)[0]


def proposed_with_contrast(
    gray: NDArray[np.uint8], params: CrackParams, surface: SurfaceStats | None = None
) -> tuple[NDArray[np.bool_], NDArray[np.float32]]:
    """``proposed_cracks`` and each pixel's darkness below its background (grey levels)."""
    z, dark, contrast = line_and_dark_spreads(gray, params, surface)
    return select_cracks(z, dark, params), contrast


def line_and_dark_spreads(
    gray: NDArray[np.uint8],
    params: CrackParams = CrackParams(),
    surface: SurfaceStats | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """Each pixel's line response and darkness in spreads of the surface (``surface``, or
    measured on the image), and its darkness below background in grey levels; each (H, W)."""
    R, norm, contrast = _line_and_light(gray, params)
    sp = surface if surface is not None else SurfaceStats.of(R, norm)
    z = (R - np.float32(sp.line_median)) * np.float32(1.0 / sp.line_spread)
    dark = (np.float32(sp.light_median) - norm) * np.float32(1.0 / sp.light_spread)
    return z, dark, contrast


def select_cracks(
    z: NDArray[np.float32], dark: NDArray[np.float32], params: CrackParams = CrackParams()
) -> NDArray[np.bool_]:
    """The connected regions of pixels with line response over ``params.grow_spreads`` and
    darkness over ``params.dark_spreads`` (both (H, W), in spreads) that are elongated and
    significant (see :class:`CrackParams`)."""
    candidates = (z > params.grow_spreads) & (dark > params.dark_spreads)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(
        candidates.view(np.uint8), connectivity=8
    )
    if n <= 1:
        return candidates
    area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
    length = np.hypot(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT])
    mean_z = np.bincount(labels.ravel(), weights=z.ravel(), minlength=n) / np.maximum(area, 1)
    keep = (mean_z * np.sqrt(length) >= params.significance) & (
        length**2 >= params.elongation * area
    )
    keep[0] = False
    return select_components(cast(NDArray[np.int32], labels), cast(NDArray[np.int32], stats), keep)
