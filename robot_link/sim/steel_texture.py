"""The steel a camera sees, without its defects: surfaces, light and the camera.

Pieces of :mod:`robot_link.sim.steel_crops` (labelled crack crops of steel): one image's
drawing context (:class:`View`), smooth noise in pixels set from millimetres, the surfaces a
bridge's steel shows (mill scale, red-oxide primer, paint, weathered paint, blasted steel,
weathering-steel patina), uneven light, and defocus, motion blur, sensor noise and JPEG.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, cast

import cv2
import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]
Pts = NDArray[np.float64]
Rng = np.random.Generator


class CameraRanges(Protocol):
    """Ranges of the camera's effects, drawn per image."""

    @property
    def blur_px(self) -> tuple[float, float]: ...  # defocus, Gaussian sigma
    @property
    def noise_grey(self) -> tuple[float, float]: ...  # sensor noise sigma
    @property
    def jpeg_quality(self) -> tuple[int, int]: ...
    @property
    def jpeg_probability(self) -> float: ...


@dataclass(frozen=True)
class View:
    """One image's drawing context: random stream, px per mm, pixel grid, light and gravity."""

    rng: Rng
    s: float  # px per mm
    xx: F32  # x of each pixel's centre
    yy: F32
    light: Pts  # unit vector towards the main light, in the image plane
    down: Pts  # unit vector of gravity in the image
    shape: tuple[int, int]
    hidden: F32  # share of each pixel's plate hidden under bolt heads and washers


def log_uniform(rng: Rng, lo: float, hi: float) -> float:
    """A value log-uniform in [lo, hi]."""
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def unit(angle: float) -> Pts:
    """Unit vector at `angle` (radians, image axes)."""
    return np.array([np.cos(angle), np.sin(angle)])


def fixed_point(p: Pts) -> tuple[int, int]:
    """A point in OpenCV's fixed point with 4 fractional bits (shift=4)."""
    return int(round(p[0] * 16)), int(round(p[1] * 16))


def spot(v: View, lo: float = 0.0, hi: float = 1.0) -> Pts:
    """A random point in the image, between fractions lo and hi of its width and height."""
    h, w = v.shape
    return np.array([v.rng.uniform(lo, hi) * w, v.rng.uniform(lo, hi) * h])


def smooth_noise(rng: Rng, shape: tuple[int, int], cell: float) -> F32:
    """Smooth noise of about unit size with features about `cell` px wide."""
    h, w = shape
    c = max(1.0, cell)
    small = rng.standard_normal((int(h / c) + 2, int(w / c) + 2), dtype=np.float32)
    return cast(F32, cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC))


def fbm(rng: Rng, shape: tuple[int, int], cell: float, octaves: int = 4) -> F32:
    """Multi-octave noise: octaves halving in size and in amplitude from `cell` px."""
    out = np.zeros(shape, np.float32)
    for o in range(octaves):
        out += 0.5**o * smooth_noise(rng, shape, cell / 2**o)
    return out


def blur(a: F32, sigma: float) -> F32:
    """Gaussian blur with sigma in px."""
    return cast(F32, cv2.GaussianBlur(a, (0, 0), sigma))


def streaks(rng: Rng, shape: tuple[int, int], along: float, across: float, deg: float) -> F32:
    """Smooth noise with features `along` px long in the direction `deg`, `across` px wide."""
    h, w = shape
    d = int(np.hypot(h, w)) + 2
    small = rng.standard_normal((int(d / max(across, 1)) + 2, int(d / along) + 2), dtype=np.float32)
    m = cv2.getRotationMatrix2D((d / 2, d / 2), deg, 1.0)
    m[:, 2] += np.array([w / 2 - d / 2, h / 2 - d / 2])
    big = cv2.resize(small, (d, d), interpolation=cv2.INTER_CUBIC)
    return cast(F32, cv2.warpAffine(big, m, (w, h), borderMode=cv2.BORDER_REFLECT))


def profile(rng: Rng, lo: float, hi: float, cell: float) -> tuple[Pts, Pts]:
    """Smooth unit noise along [lo, hi] with features about `cell` long, as (knots, values)."""
    k = int((hi - lo) / cell * 4) + 33
    g = np.exp(-0.5 * (np.arange(-12, 13) / 4.0) ** 2)
    vals = np.convolve(rng.standard_normal(k), g, "same") / np.sqrt(np.sum(g * g))
    return lo + (np.arange(k) - 16) * cell / 4, vals


def relief(height: F32, light: Pts) -> F32:
    """Shading of a height field lit from `light`, scaled to at most 1."""
    gx, gy = cv2.Sobel(height, cv2.CV_32F, 1, 0), cv2.Sobel(height, cv2.CV_32F, 0, 1)
    shade = -(gx * light[0] + gy * light[1])
    return cast(F32, shade / (float(np.abs(shade).max()) + 1e-6))


def grain(v: View, mm: float) -> F32:
    """Fine grain of about `mm` (at least half a pixel), unit std."""
    g = blur(v.rng.standard_normal(v.shape, dtype=np.float32), max(0.5, mm * v.s))
    return cast(F32, g / (float(g.std()) + 1e-6))


def hex_distance(dx: F32, dy: F32, phi: float) -> F32:
    """Distance from a hexagon's centre along its nearest flat's normal (a hexagonal norm)."""
    a, b, c = (np.abs(dx * np.cos(t) + dy * np.sin(t)) for t in phi + np.arange(3) * np.pi / 3)
    return cast(F32, np.maximum(np.maximum(a, b), c))


def mill_scale(v: View) -> F32:
    """Mill scale: dark blue-grey, mottled, flaked off in patches (lighter steel, darker rust)."""
    r, sh, s = v.rng, v.shape, v.s
    img = r.uniform(60, 100) + 8 * fbm(r, sh, 10 * s) + 3 * grain(v, 0.05)
    flakes = np.clip((fbm(r, sh, 6 * s, 3) - r.uniform(0.8, 1.6)) * 3, 0, 1)  # steel or rust
    return cast(F32, img + float(r.choice([-0.5, 1.0])) * r.uniform(10, 35) * flakes)


def primer(v: View) -> F32:
    """Red-oxide primer in grey: mid-tone with a fine orange-peel texture."""
    r, sh, s = v.rng, v.shape, v.s
    peel = relief(smooth_noise(r, sh, r.uniform(0.6, 1.5) * s), v.light)
    return cast(F32, r.uniform(80, 130) + 5 * fbm(r, sh, 25 * s, 3) + r.uniform(3, 8) * peel)


def paint(v: View) -> F32:
    """Paint: light to mid grey, smooth, with roller or brush marks along one direction."""
    r, sh, s = v.rng, v.shape, v.s
    deg = float(r.choice([0.0, 90.0]) + r.normal(0, 10))
    marks = streaks(r, sh, r.uniform(15, 60) * s, r.uniform(0.5, 2.5) * s, deg)
    img = r.uniform(110, 185) + 5 * fbm(r, sh, 30 * s, 3) + r.uniform(1.5, 5) * marks
    return cast(F32, img + 1.5 * grain(v, 0.1))


def weathered(v: View) -> F32:
    """Weathered paint: chalked (paler, patchy) and rusty where worn through, with pits."""
    r, sh, s = v.rng, v.shape, v.s
    img = paint(v)
    chalk = np.clip(0.5 + 0.5 * fbm(r, sh, 15 * s, 3), 0, 1) * r.uniform(0.1, 0.45)
    rust = np.clip((fbm(r, sh, 5 * s, 3) - r.uniform(1.0, 1.8)) * 3, 0, 1)
    img = cast(F32, img * (1 - chalk) + 215 * chalk - r.uniform(30, 70) * rust)
    pitting(img, v, int(r.integers(2, 8)))
    return img


def blasted(v: View) -> F32:
    """Blast-cleaned bare steel: light grey with a fine sharp grain."""
    r = v.rng
    img = r.uniform(105, 165) + r.uniform(5, 12) * grain(v, 0.06)
    return cast(F32, img + 4 * fbm(r, v.shape, 12 * v.s, 3))


def patina(v: View) -> F32:
    """Weathering-steel patina: dark brown (dark grey), strongly mottled and granular."""
    r, sh, s = v.rng, v.shape, v.s
    spots = np.clip(smooth_noise(r, sh, r.uniform(1, 4) * s) - 1.0, 0, None)
    img = r.uniform(50, 95) + 12 * fbm(r, sh, 15 * s) + 5 * grain(v, 0.1)
    return cast(F32, img - r.uniform(10, 30) * spots)


Surface = Callable[[View], F32]
SURFACES: list[Surface] = [mill_scale, primer, paint, weathered, blasted, patina]


def pitting(img: F32, v: View, clusters: int) -> None:
    """Corrosion pitting: clusters of small dark pits."""
    r, sink = v.rng, np.zeros(v.shape, np.uint8)
    for _ in range(clusters):
        n = int(r.integers(5, 60))
        pts = spot(v) + r.normal(0, r.uniform(2, 10) * v.s, (n, 2))
        for p, rad in zip(pts, r.uniform(0.1, 0.6, n) * v.s):
            depth = int(r.integers(25, 90))
            cv2.circle(sink, fixed_point(p), max(4, int(rad * 16)), depth, -1, cv2.LINE_AA, 4)
    img -= sink


def uneven_light(img: F32, v: View) -> None:
    """Uneven illumination: smooth gain field, tilt, vignetting and at times a specular highlight."""
    r, (h, w) = v.rng, v.shape
    x, y = (v.xx - w / 2) / w, (v.yy - h / 2) / h
    gain = 1 + r.uniform(0.03, 0.15) * smooth_noise(r, v.shape, 0.5 * max(h, w))
    img *= (gain + r.normal(0, 0.1) * x + r.normal(0, 0.1) * y) * (
        1 - r.uniform(0, 0.7) * (x * x + y * y)
    )
    if r.random() < 0.3:
        sx, sy, sig = r.uniform(-0.5, 0.5), r.uniform(-0.5, 0.5), r.uniform(0.05, 0.3)
        img += r.uniform(20, 70) * np.exp(-((x - sx) ** 2 + (y - sy) ** 2) / (2 * sig * sig))


def camera_effects(img: F32, v: View, p: CameraRanges) -> NDArray[np.uint8]:
    """Defocus, occasional motion blur, sensor noise and JPEG re-compression, to 8 bits."""
    r = v.rng
    sigma = r.uniform(*p.blur_px)
    if sigma > 0.1:
        img = blur(img, sigma)
    if r.random() < 0.15:
        k, a = int(r.integers(2, 7)), unit(r.uniform(0, np.pi))
        ker = np.zeros((2 * k + 1, 2 * k + 1), np.float32)
        cv2.line(ker, fixed_point(k - k * a), fixed_point(k + k * a), 1.0, 1, cv2.LINE_8, 4)
        img = cast(F32, cv2.filter2D(img, -1, ker / ker.sum()))
    img = img + r.uniform(*p.noise_grey) * r.standard_normal(v.shape, dtype=np.float32)
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    if r.random() < p.jpeg_probability:
        q = int(r.integers(p.jpeg_quality[0], p.jpeg_quality[1] + 1))
        jpeg = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, q])[1]
        out = cast(NDArray[np.uint8], cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE))
    return out
