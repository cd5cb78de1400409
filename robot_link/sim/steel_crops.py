"""Labelled crops of steel bridge surfaces for crack segmentation: grey images, exact crack masks.

Each image is one camera view of steel at ``mm_per_px`` (drawn per image): a surface, hard
negatives that look like cracks on steel (weld beads with dark toe lines, bolt heads with
shadows, plate edges, scratches, paint runs, rust streaks, pitting, crazing, stains) and, in a
share ``crack_probability`` of the images, fatigue cracks: along a weld toe, out from a bolt, or
free in the plate. Sizes are in mm, so a 0.05 mm hairline is sub-pixel and darkens a pixel by
the share of it that it covers. Truth: where a crack's 4x-supersampled coverage reaches half a
pixel, and its 1-px centre line (so a hairline is labelled along its whole length; every such
pixel is darkened by at least ``_FAINTEST``). Cracks are drawn before the light and the camera. The surfaces, light and camera are
:mod:`robot_link.sim.steel_texture`; the hard negatives :mod:`robot_link.sim.steel_features`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from robot_link.sim.steel_features import (
    Weld,
    bolt_row,
    crazing,
    paint_runs,
    plate_edge,
    rust_streaks,
    scratches,
    stains,
    weld_bead,
)
from robot_link.sim.steel_texture import (
    F32,
    SURFACES,
    Pts,
    Rng,
    View,
    blur,
    camera_effects,
    fixed_point,
    log_uniform,
    mill_scale,
    pitting,
    profile,
    uneven_light,
    unit,
)

_SS = 4  # supersampling of a crack's coverage
_FAINTEST = 0.03  # least share of the light a crack's centre line takes away
_STEP = 2.0  # px between a crack's vertices


@dataclass(frozen=True)
class SteelCropParams:
    """Ranges drawn per image (uniform unless noted): lengths in mm on the steel, grey levels."""

    size_px: tuple[int, int] = (384, 512)  # (H, W) of each image
    mm_per_px: tuple[float, float] = (0.1, 0.4)  # the camera's resolution on the steel, log-uniform
    crack_probability: float = 0.75  # share of images with at least one crack
    crack_width_mm: tuple[float, float] = (0.05, 1.0)  # widest opening of a crack, log-uniform
    crack_length_mm: tuple[float, float] = (10.0, 150.0)  # weld-toe and free cracks, log-uniform
    bolt_crack_mm: tuple[float, float] = (5.0, 60.0)  # radial cracks from a bolt, log-uniform
    crack_depth: tuple[float, float] = (0.25, 0.9)  # light a covered pixel loses, log-uniform
    weld_width_mm: tuple[float, float] = (6.0, 12.0)  # bead width
    bolt_flats_mm: tuple[float, float] = (32.0, 41.0)  # bolt head across flats (M20-M24)
    distractors: float = 1.0  # factor on each hard negative's probability (0: bare surfaces)
    blur_px: tuple[float, float] = (0.0, 1.0)  # defocus, Gaussian sigma
    noise_grey: tuple[float, float] = (1.0, 5.0)  # sensor noise sigma
    jpeg_quality: tuple[int, int] = (60, 95)
    jpeg_probability: float = 0.5


@dataclass(frozen=True)
class _Crack:
    """A crack's centre line (px), opening width (px) and visibility (0-1) at each vertex."""

    pts: Pts
    width: Pts
    seen: Pts


def _walk(rng: Rng, start: Pts, heading: float, length: float, s: float) -> Pts:
    """A crack's meandering centre line from `start`: slow meander, small jags, rare kinks."""
    arc = np.arange(max(2, int(length / _STEP) + 1)) * _STEP
    th = heading + rng.uniform(0.05, 0.3) * np.interp(arc, *profile(rng, 0, arc[-1], 6 * s))
    th += rng.uniform(0.05, 0.25) * np.interp(arc, *profile(rng, 0, arc[-1], s))
    kinks = rng.random(arc.size) < _STEP / (30 * s)  # one every 30 mm on average
    th += np.cumsum(np.where(kinks, rng.normal(0, 0.25, arc.size), 0))
    steps = np.stack([np.cos(th), np.sin(th)], 1)[:-1]
    return start + np.vstack([np.zeros(2), np.cumsum(steps * _STEP, 0)])


def _crack(v: View, pts: Pts, widest: float, root: bool) -> _Crack:
    """A crack on `pts`, tapering to both tips (or from its root), at times faint under paint."""
    t, seen = np.linspace(0, 1, len(pts)), np.ones(len(pts))
    taper = 0.15 + 0.85 * ((1 - t) ** 0.7 if root else np.sin(np.pi * t) ** 0.5)
    if v.rng.random() < 0.4:
        arc = np.arange(len(pts)) * _STEP
        paint = np.interp(arc, *profile(v.rng, 0, arc[-1] + 1, 8 * v.s)) - v.rng.uniform(0, 0.8)
        seen -= (1 - v.rng.uniform(0.3, 0.6)) * np.clip(paint * 3, 0, 1)  # fading in and out
    return _Crack(pts, widest * taper, seen)


def _in_view(pts: Pts, shape: tuple[int, int], margin: float = 2.0) -> NDArray[np.bool_]:
    """Which points lie inside the image, `margin` px from its border."""
    inside = (pts >= margin) & (pts <= np.array(shape[::-1]) - 1 - margin)
    return cast(NDArray[np.bool_], np.all(inside, 1))


def _open(pts: Pts, v: View) -> NDArray[np.bool_]:
    """Which points lie in view on plate that no bolt hides."""
    ij = np.clip(np.rint(pts).astype(int), 0, np.array(v.shape[::-1]) - 1)
    return _in_view(pts, v.shape) & (v.hidden[ij[:, 1], ij[:, 0]] < 0.5)


def _free_crack(v: View, p: SteelCropParams, widest: float) -> _Crack:
    """A crack free in the plate, through a point in view, tapering to both tips."""
    r, length = v.rng, log_uniform(v.rng, *p.crack_length_mm) * v.s
    pts = _walk(r, np.zeros(2), r.uniform(0, 2 * np.pi), length, v.s)
    spots = r.uniform(0.1, 0.9, (32, 2)) * v.shape[::-1]
    pts += spots[int(np.argmax(_open(spots, v)))] - pts[int(r.uniform(0.3, 0.7) * len(pts))]
    return _crack(v, pts, widest, root=False)


def _weld_crack(v: View, p: SteelCropParams, weld: Weld, widest: float) -> _Crack | None:
    """A fatigue crack along one toe of a weld, within about 1 mm of it, slightly meandering."""
    r, s, diag = v.rng, v.s, float(np.hypot(*v.shape))
    us, side = np.linspace(-diag, diag, 257), float(r.choice([-1.0, 1.0]))
    ok = _open(weld.point(us, side * weld.half_at(us)), v)
    if not ok.any():
        return None
    length = log_uniform(r, *p.crack_length_mm) * s
    u = float(r.choice(us[ok])) + np.arange(-length / 2, length / 2, _STEP)
    off = r.uniform(-0.2, 0.6) + 0.3 * np.interp(u, *profile(r, u[0], u[-1] + 1, 4 * s))
    off += 0.08 * np.interp(u, *profile(r, u[0], u[-1] + 1, 0.6 * s))  # mm from the toe
    pts = weld.point(u, side * (weld.half_at(u) + np.clip(off, -1.0, 1.0) * s))
    return _crack(v, pts, widest, root=False)


def _bolt_crack(v: View, p: SteelCropParams, bolt: tuple[Pts, float], widest: float) -> _Crack:
    """A crack running radially out from under a bolt head or washer, widest at its root."""
    r, (c, rad) = v.rng, bolt
    ang = r.uniform(0, 2 * np.pi, 32)
    starts = c + (rad + 0.5) * np.stack([np.cos(ang), np.sin(ang)], 1)
    ok = np.flatnonzero(_open(starts, v))
    if ok.size == 0:
        return _free_crack(v, p, widest)
    length = log_uniform(r, *p.bolt_crack_mm) * v.s
    pts = _walk(r, starts[ok[0]], float(ang[ok[0]]) + r.normal(0, 0.15), length, v.s)
    return _crack(v, pts, widest, root=True)


def _branch(v: View, c: _Crack) -> _Crack:
    """A thinner side branch leaving a crack somewhere along its middle."""
    r, n = v.rng, len(c.pts)
    i = int(r.integers(n // 4, 3 * n // 4 + 1))
    d = c.pts[min(i + 1, n - 1)] - c.pts[max(i - 1, 0)]
    turn = float(r.choice([-1.0, 1.0])) * r.uniform(0.35, 0.9)
    pts = _walk(
        r, c.pts[i], float(np.arctan2(d[1], d[0])) + turn, r.uniform(0.15, 0.5) * n * _STEP, v.s
    )
    taper = 0.15 + 0.85 * (1 - np.linspace(0, 1, len(pts))) ** 0.7
    return _Crack(pts, c.width[i] * r.uniform(0.4, 0.8) * taper, np.full(len(pts), c.seen[i]))


def _draw_crack(dark: F32, truth: NDArray[np.uint8], c: _Crack, depth: float) -> None:
    """Darken by the crack's 4x-supersampled coverage times `depth`; mark coverage >= 0.5."""
    (h, w), pad = dark.shape, float(c.width.max()) / 2 + 2
    near = _in_view(c.pts, (h, w), -pad)
    seg = np.flatnonzero(near[:-1] | near[1:])
    if seg.size == 0:
        return
    ends = np.vstack([c.pts[seg], c.pts[seg + 1]])
    x0, y0 = np.clip(np.floor(ends.min(0) - pad).astype(int), 0, None)
    x1, y1 = np.minimum(np.ceil(ends.max(0) + pad).astype(int) + 1, (w, h))
    cover = np.zeros(((y1 - y0) * _SS, (x1 - x0) * _SS), np.float32)
    geo = np.zeros(cover.shape, np.uint8)
    q = (c.pts - (x0, y0)) * _SS + (_SS - 1) / 2  # pixel centres at the canvas's scale
    for i in seg:
        wide = _SS * (c.width[i] + c.width[i + 1]) / 2
        thick = max(1, int(round(wide)))
        a, b = fixed_point(q[i]), fixed_point(q[i + 1])
        cv2.line(cover, a, b, min(1.0, wide / thick) * float(c.seen[i]), thick, cv2.LINE_8, 4)
        cv2.line(geo, a, b, 1, thick, cv2.LINE_8, 4)
    size = (x1 - x0, y1 - y0)
    area = cv2.resize(cover, size, interpolation=cv2.INTER_AREA)
    frac = cv2.resize(geo.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    np.maximum(dark[y0:y1, x0:x1], depth * area, out=dark[y0:y1, x0:x1])
    truth[y0:y1, x0:x1] |= (frac >= 0.5).astype(np.uint8)


def _cracks(
    img: F32,
    v: View,
    p: SteelCropParams,
    welds: list[Weld],
    bolts: list[tuple[Pts, float]],
) -> NDArray[np.bool_]:
    """One to three cracks (weld toe, bolt, free; some branching), hidden under bolts; truth."""
    r, dark = v.rng, np.zeros(v.shape, np.float32)
    truth, centre = np.zeros(v.shape, np.uint8), np.zeros(v.shape, np.uint8)
    for _ in range(1 + int(r.random() < 0.25) + int(r.random() < 0.08)):
        kinds = ["free"] + ["weld"] * 3 * bool(welds) + ["bolt"] * 2 * bool(bolts)
        kind, widest = kinds[int(r.integers(len(kinds)))], log_uniform(r, *p.crack_width_mm) * v.s
        c: _Crack | None = None
        if kind == "weld":
            c = _weld_crack(v, p, welds[int(r.integers(len(welds)))], widest)
        elif kind == "bolt":
            c = _bolt_crack(v, p, bolts[int(r.integers(len(bolts)))], widest)
        c = c if c is not None else _free_crack(v, p, widest)
        depth = log_uniform(r, *p.crack_depth)
        for part in [c, _branch(v, c)] if r.random() < 0.15 else [c]:
            _draw_crack(dark, truth, part, depth)
            line = np.rint(part.pts * 16).astype(np.int32)
            cv2.polylines(centre, [line], False, 1, 1, cv2.LINE_8, 4)
    if r.random() < 0.3:  # rust or dirt bled out of the crack
        np.maximum(dark, 0.35 * blur(dark, r.uniform(0.2, 1.0) * v.s), out=dark)
    on = centre.astype(bool)
    dark[on] = np.maximum(dark[on], _FAINTEST)
    img *= 1 - dark * (1 - v.hidden)
    return ((truth | centre) > 0) & (v.hidden < 0.5)


def steel_sample(
    seed: int, params: SteelCropParams = SteelCropParams()
) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
    """(H, W) uint8 grey image and (H, W) bool crack truth for one seed (deterministic)."""
    r, (h, w) = np.random.default_rng(seed), params.size_px
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    light = unit(r.uniform(0, 2 * np.pi))
    down = unit(np.pi / 2 + (r.normal(0, 0.15) if r.random() < 0.7 else r.uniform(-np.pi, np.pi)))
    s, hidden = 1.0 / log_uniform(r, *params.mm_per_px), np.zeros((h, w), np.float32)
    v = View(r, s, xx, yy, light, down, (h, w), hidden)
    surface = SURFACES[int(r.integers(len(SURFACES)))]
    img = surface(v).astype(np.float32)

    def drawn(probability: float) -> bool:
        """Whether a hard negative of this probability (times params.distractors) is drawn."""
        return bool(r.random() < probability * params.distractors)

    if drawn(0.4):
        stains(img, v)
    if drawn(0.8 if surface is mill_scale else 0.2):
        crazing(img, v)
    if drawn(0.35):
        pitting(img, v, int(r.integers(1, 4)))
    if drawn(0.3):
        plate_edge(img, v)
    welds = [
        weld_bead(img, v, params.weld_width_mm) for _ in range(int(drawn(0.65)) + int(drawn(0.15)))
    ]
    bolts = bolt_row(img, v, params.bolt_flats_mm) if drawn(0.35) else []
    for probability, element in [(0.3, rust_streaks), (0.25, paint_runs), (0.6, scratches)]:
        if drawn(probability):
            element(img, v)
    truth = np.zeros((h, w), bool)
    if r.random() < params.crack_probability:
        truth = _cracks(img, v, params, welds, bolts)
    uneven_light(img, v)
    return camera_effects(img, v, params), truth


def steel_samples(
    n: int, seed: int, params: SteelCropParams = SteelCropParams()
) -> list[tuple[str, NDArray[np.uint8], NDArray[np.bool_]]]:
    """n samples named f"steel-{seed}-{k:05d}", sample k from seed derived from (seed, k)."""
    out = []
    for k in range(n):
        sub = int(np.random.SeedSequence([seed, k]).generate_state(1, np.uint64)[0])
        out.append((f"steel-{seed}-{k:05d}", *steel_sample(sub, params)))
    return out
