"""Image-only guesses of how two overlapping frames sit relative to each other, by phase
correlation (the stitcher's initial overlap estimate when there is no odometry): the
shift of the strongest correlation peaks, each checked by the correlation of the overlap
it implies, with frame b turned around (a robot turns at lane ends) and tilted by a few
degrees when nothing is sure. Registration (:mod:`processing.stitching.alignment`) verifies them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.poses import wrap_angle

Gray = NDArray[np.float32]

# cv2.rotate codes, k quarter turns
QUARTER_TURNS = (
    None,
    cv2.ROTATE_90_CLOCKWISE,
    cv2.ROTATE_180,
    cv2.ROTATE_90_COUNTERCLOCKWISE,
)


def quarter_turned(image: Gray, k: int) -> Gray:
    """``image`` turned by k (0 to 3) quarter turns clockwise on screen, exactly (no
    interpolation)."""
    code = QUARTER_TURNS[k]
    return image if code is None else cast(Gray, cv2.rotate(image, code))


def _tukey(n: int, taper: float) -> NDArray[np.float32]:
    """A window flat in the middle, with cosine tapers over ``taper`` of each end."""
    x = np.arange(n, dtype=np.float64)
    m = max(taper * n, 1.0)
    w = np.ones(n)
    w[x < m] = 0.5 - 0.5 * np.cos(np.pi * x[x < m] / m)
    w[x >= n - m] = 0.5 - 0.5 * np.cos(np.pi * (n - 1 - x[x >= n - m]) / m)
    return w.astype(np.float32)


@lru_cache(maxsize=8)
def _window(h: int, w: int) -> NDArray[np.float32]:
    """The tapered window of phase correlation for an (h, w) image (read only)."""
    win = np.outer(_tukey(h, 0.1), _tukey(w, 0.1))
    win.flags.writeable = False
    return win


def _spectrum(image: Gray) -> NDArray[np.float32]:
    """Fourier transform (OpenCV's two-channel complex layout) of the windowed image, its
    mean removed: one side of a phase correlation."""
    image = np.asarray(image, np.float32)
    mean = float(cv2.mean(image)[0])
    centred = cv2.subtract(image, mean)  # type: ignore[call-overload]  # OpenCV's stubs lack the scalar form
    windowed = cv2.multiply(centred, _window(*image.shape))
    return cast(NDArray[np.float32], cv2.dft(windowed, flags=cv2.DFT_COMPLEX_OUTPUT))


def _correlation_peaks(
    Fa: NDArray[np.float32], Fb: NDArray[np.float32], count: int
) -> list[tuple[float, float]]:
    """The ``count`` strongest peaks (shift of b's content relative to a's, modulo the image
    size) of the phase correlation surface of two :func:`_spectrum`, by non-maximum suppression."""
    cross = cast(NDArray[np.float32], cv2.mulSpectrums(Fa, Fb, 0, conjB=True))
    magnitude = cv2.magnitude(cross[..., 0], cross[..., 1])
    np.maximum(magnitude, 1e-9, out=magnitude)
    cross /= magnitude[..., None]
    surface = cv2.idft(cross, flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE)
    surface = cv2.GaussianBlur(surface, (0, 0), 1.0)  # rotation and noise spread the peak
    local = surface == cv2.dilate(surface, np.ones((9, 9), np.uint8))
    ys, xs = np.nonzero(local)
    order = np.argsort(-surface[ys, xs])[:count]
    return [(float(xs[i]), float(ys[i])) for i in order]


def _correlation(a: Gray, b: Gray) -> float:
    """Correlation coefficient of two images of one size (``cv2.TM_CCOEFF_NORMED`` of
    equal sizes, 5x faster: no transform)."""
    mean_a, std_a = cv2.meanStdDev(a)
    mean_b, std_b = cv2.meanStdDev(b)
    covariance = cv2.mean(cv2.multiply(a, b))[0] - mean_a[0, 0] * mean_b[0, 0]
    return float(covariance / max(std_a[0, 0] * std_b[0, 0], 1e-12))


# phase correlation at a quarter of the resolution, at half where that places nothing
PHASE_SCALES = (
    4,
    2,
)


@dataclass(frozen=True)
class PhaseView:
    """A frame prepared for :func:`phase_candidates`: reduced ``scale`` times, smoothed
    for scoring candidate overlaps, and its spectrum (each frame is in two consecutive
    pairs: prepared once)."""

    small: Gray
    smooth: Gray
    spectrum: NDArray[np.float32]
    scale: int

    @classmethod
    def of(cls, gray: Gray, scale: int = 2, *, reduced: int = 1) -> PhaseView:
        """Prepare a grey image (already ``reduced`` times smaller than full resolution)
        at 1/``scale`` of full resolution (both powers of two)."""
        small = np.asarray(gray, np.float32)
        while reduced < scale:
            small, reduced = cast(Gray, cv2.pyrDown(small)), 2 * reduced
        smooth = cast(Gray, cv2.GaussianBlur(small, (0, 0), 4.0 / scale))
        return cls(small, smooth, _spectrum(small), scale)


# small turns tried where frame b, as it is, finds nothing sure
PHASE_TILTS = tuple(np.radians([0.0, 6.0, -6.0]))
# a candidate ends the search only if its overlap is this share of the frame (tiny ones correlate by
# chance)
SURE_OVERLAP = 0.15


def phase_candidates(
    gray_a: Gray | PhaseView,
    gray_b: Gray | PhaseView,
    *,
    turns: Sequence[int] = (0, 2),
    keep: int = 4,
    sure: float = 0.8,
    tilts: Sequence[float] = PHASE_TILTS,
) -> list[tuple[NDArray[np.float64], float]]:
    """Image-only guesses of the relative pose (dx, dy, θ) of frame b in frame a, best
    first, with their overlap correlation.

    Frame b is tried as it is and turned by each of ``turns`` quarter turns (a robot
    driving lanes turns around at their ends; quarter turns of a non-square frame are
    skipped), then all of that tilted by each of ``tilts`` (radians: phase correlation
    loses frames turned more than a few degrees from each other), in that order, until
    one gives a candidate correlating at least ``sure`` over at least
    :data:`SURE_OVERLAP` of the frame (a frame turned around correlates at most ~0.7
    unturned, measured; small overlaps correlate by chance). The strongest peaks of the
    phase correlation surface (tapered window, so an overlap at the frame's edge still
    counts) are taken,
    each wrap-around reading of a peak (a 400 px shift of a 640 px frame reads as -240 px)
    is scored by the normalised correlation of the overlap it implies, on smoothed images
    so that a small rotation does not decorrelate fine texture. Grey images are worked on
    at half resolution; prepared views (of one scale) at theirs.
    """
    va = gray_a if isinstance(gray_a, PhaseView) else PhaseView.of(gray_a)
    vb = gray_b if isinstance(gray_b, PhaseView) else PhaseView.of(gray_b, va.scale)
    if va.scale != vb.scale:
        raise ValueError(f"views of different scales: {va.scale} and {vb.scale}")
    h, w = va.small.shape
    found: list[tuple[NDArray[np.float64], float, float]] = []
    for tilt, k in [(tilt, k) for tilt in tilts for k in turns if k % 2 == 0 or w == h]:
        if k == 0 and tilt == 0.0:
            Fb, b_s = vb.spectrum, vb.smooth
        else:  # turning commutes with the (isotropic, mirror-bordered) smoothing
            small, b_s = quarter_turned(vb.small, k), quarter_turned(vb.smooth, k)
            if tilt != 0.0:
                small, b_s = _tilted(small, tilt), _tilted(b_s, tilt)
            Fb = _spectrum(small)
        found += _score_peaks(va, Fb, b_s, float(wrap_angle(-k * np.pi / 2 - tilt)))
        if any(score >= sure and share >= SURE_OVERLAP for _, score, share in found):
            break
    found.sort(key=lambda c: -c[1])
    return [(delta, score) for delta, score, _ in found[:keep]]


def _tilted(image: Gray, angle: float) -> Gray:
    """``image`` turned about its centre by ``angle`` (radians, counter-clockwise on
    screen; borders mirrored): what a frame turned by -``angle`` relative to it sees."""
    h, w = image.shape
    R = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), float(np.degrees(angle)), 1.0)
    return cast(
        Gray,
        cv2.warpAffine(image, R, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT),
    )


def _score_peaks(
    va: PhaseView, Fb: NDArray[np.float32], b_s: Gray, theta: float
) -> list[tuple[NDArray[np.float64], float, float]]:
    """Candidates (dx, dy, ``theta``) from the phase correlation peaks of view a with a
    prepared frame b (spectrum, smoothed image): each wrap-around reading with its score
    and the share of the frame its overlap covers."""
    h, w = va.small.shape
    out = []
    for px, py in _correlation_peaks(va.spectrum, Fb, 4):
        for dx in (px, px - w):
            for dy in (py, py - h):
                ix, iy = round(dx), round(dy)
                ow, oh = w - abs(ix), h - abs(iy)
                if ow < 8 or oh < 8 or ow * oh < 0.08 * w * h:
                    continue
                pa = va.smooth[max(iy, 0) : max(iy, 0) + oh, max(ix, 0) : max(ix, 0) + ow]
                pb = b_s[max(-iy, 0) : max(-iy, 0) + oh, max(-ix, 0) : max(-ix, 0) + ow]
                out.append(
                    (
                        np.array([va.scale * dx, va.scale * dy, theta]),
                        _correlation(pa, pb),
                        ow * oh / (w * h),
                    )
                )
    return out
