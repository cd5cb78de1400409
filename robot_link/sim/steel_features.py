"""Hard negatives on steel: what looks like a crack and is not.

Weld beads with dark toe lines and spatter, bolt heads with washers and cast shadows, plate
edges, scratches, paint runs, rust streaks, pitting, crazing of mill scale and stains, drawn
into a float image by :mod:`robot_link.sim.steel_crops`; sizes in millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np

from robot_link.sim.steel_texture import (
    F32,
    Pts,
    View,
    blur,
    fixed_point,
    hex_distance,
    log_uniform,
    profile,
    relief,
    smooth_noise,
    spot,
    unit,
)


@dataclass(frozen=True)
class Weld:
    """A bead's axis (origin, direction t, normal n, bow in 1/px) and its half width in px."""

    p0: Pts
    t: Pts
    n: Pts
    bow: float
    half: float
    wobble: tuple[Pts, Pts]  # relative change of the width along the axis (knots, values)

    def half_at(self, u: Pts) -> Pts:
        """Half width (px) at positions u along the axis."""
        return self.half * (1 + 0.06 * np.interp(u, *self.wobble))

    def point(self, u: Pts, d: Pts) -> Pts:
        """Image points at u along the axis and d across it."""
        return self.p0 + u[:, None] * self.t + (d + self.bow * u * u)[:, None] * self.n


def stains(img: F32, v: View) -> None:
    """Stains: soft blotches a little darker or lighter than the surface."""
    r = v.rng
    blob = np.clip(smooth_noise(r, v.shape, r.uniform(10, 40) * v.s) - r.uniform(0.3, 0.9), 0, 0.5)
    img += float(r.choice([-1.0, 1.0])) * r.uniform(16, 50) * blob


def crazing(img: F32, v: View) -> None:
    """Crazing of mill scale or paint: faint short-segmented polygonal network (not cracks)."""
    r, (h, w) = v.rng, v.shape
    cell = r.uniform(2, 8) * v.s
    seeds, k = np.ones((h, w), np.uint8), int(h * w / cell**2) + 2
    seeds[r.integers(0, h, k), r.integers(0, w, k)] = 0
    cells = cv2.distanceTransformWithLabels(seeds, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    labels, edge = cells[1], np.zeros((h, w), bool)
    edge[:, 1:] |= labels[:, 1:] != labels[:, :-1]
    edge[1:] |= labels[1:] != labels[:-1]
    edge &= smooth_noise(r, (h, w), 0.7 * cell) > r.uniform(0.2, 0.6)
    img -= r.uniform(3, 10) * blur(edge.astype(np.float32), 0.6)


def plate_edge(img: F32, v: View) -> None:
    """A plate edge or step across the image: dark gap, shadow on the low side, brightness change."""
    r, s = v.rng, v.s
    n, p0 = unit(float(r.choice([0.0, np.pi / 2]) + r.normal(0, 0.1))), spot(v, 0.1, 0.9)
    d = (v.xx - p0[0]) * n[0] + (v.yy - p0[1]) * n[1]
    low = np.clip(d + 0.5, 0, 1)
    img *= 1 + r.uniform(-0.3, 0.3) * low
    img *= 1 - r.uniform(0.3, 0.7) * np.exp(-0.5 * (d / (r.uniform(0.15, 1.0) * s + 0.3)) ** 2)
    img *= 1 - r.uniform(0.1, 0.35) * low * np.exp(-np.maximum(d, 0) / (r.uniform(0.5, 4) * s))


def weld_bead(img: F32, v: View, width_mm: tuple[float, float]) -> Weld:
    """A weld bead across the image: rippled bead, dark toe lines at both edges, spatter beside."""
    r, s = v.rng, v.s
    a = float(r.choice([0.0, np.pi / 2]) + r.normal(0, 0.12))
    a = a if r.random() < 0.7 else r.uniform(0, np.pi)
    diag = float(np.hypot(*v.shape))
    bow = r.uniform(-1, 1) / (2 * log_uniform(r, 300, 3000) * s)
    half, wobble = 0.5 * r.uniform(*width_mm) * s, profile(r, -diag, diag, 15 * s)
    weld = Weld(spot(v, 0.15, 0.85), unit(a), unit(a + np.pi / 2), bow, half, wobble)
    dx, dy = v.xx - weld.p0[0], v.yy - weld.p0[1]
    u = dx * weld.t[0] + dy * weld.t[1]
    d = dx * weld.n[0] + dy * weld.n[1] - weld.bow * u * u
    hw = weld.half_at(u).astype(np.float32)
    rr = d / hw
    hgt = np.sqrt(np.clip(1 - rr * rr, 0, None))
    inside = np.clip((1 - np.abs(rr)) * hw + 0.5, 0, 1)
    ripple = np.cos(2 * np.pi * (u + hw * rr * rr) / (r.uniform(0.8, 2.5) * s))  # arcs
    slope = np.clip(-rr / np.maximum(hgt, 0.25), -3, 3) * float(v.light @ weld.n)
    bead = r.uniform(70, 190) + r.uniform(4, 12) * ripple * hgt + 12 * slope
    cover = inside * r.uniform(0.4, 0.8)  # the surface's coat shows through the rest
    img[:] = img * (1 - cover) + cover * (bead + 4 * smooth_noise(r, v.shape, 0.7 * s))
    toe = np.exp(-0.5 * ((np.abs(d) - hw) / (r.uniform(0.15, 0.45) * s)) ** 2)
    depth = np.where(d > 0, r.uniform(0.15, 0.5), r.uniform(0.15, 0.5))
    img *= 1 - depth * toe * np.clip(0.75 + 0.35 * smooth_noise(r, v.shape, 4 * s), 0.2, 1)
    k = int(r.poisson(r.uniform(0, 15)))
    us = r.uniform(float(u.min()), float(u.max()), k)
    ds = r.choice([-1.0, 1.0], k) * (weld.half_at(us) + r.exponential(3 * s, k))
    lift, sink = np.zeros(v.shape, np.uint8), np.zeros(v.shape, np.uint8)
    for q, rad in zip(weld.point(us, ds), r.uniform(0.2, 0.7, k) * s):
        cv2.circle(
            sink, fixed_point(q - v.light * rad), max(8, int(rad * 16)), 40, -1, cv2.LINE_AA, 4
        )
        bright = int(r.integers(25, 70))
        cv2.circle(lift, fixed_point(q), max(8, int(rad * 16)), bright, -1, cv2.LINE_AA, 4)
    img += lift.astype(np.float32) - sink
    return weld


def bolt_row(img: F32, v: View, flats_mm: tuple[float, float]) -> list[tuple[Pts, float]]:
    """One to three bolts in a row at 70-100 mm pitch; their centres and outer radii."""
    r = v.rng
    step, c0 = unit(r.uniform(0, np.pi)) * r.uniform(70, 100) * v.s, spot(v, 0.1, 0.9)
    flats, hexagon, washer = r.uniform(*flats_mm) * v.s, r.random() < 0.7, r.random() < 0.6
    centres = [c0 + (i - 1) * step for i in range(int(r.integers(1, 4)))]
    return [(c, _bolt(img, v, c, flats, hexagon, washer or not hexagon)) for c in centres]


def _bolt(img: F32, v: View, c: Pts, flats: float, hexagon: bool, washer: bool) -> float:
    """A bolt head (hexagon, or domed) with or without a washer, its cast shadow and contact ring."""
    r, (h, w), s = v.rng, v.shape, v.s
    rw, rh = flats * r.uniform(0.55, 0.62) * washer, flats / (np.sqrt(3) if hexagon else 2)
    outer, phi, throw = max(rw, rh), r.uniform(0, np.pi / 3), v.light * r.uniform(0.08, 0.3) * flats
    m = outer + float(np.abs(throw).max()) + 4 * s + 2
    x0, y0 = max(0, int(c[0] - m)), max(0, int(c[1] - m))
    x1, y1 = min(w, int(c[0] + m) + 1), min(h, int(c[1] + m) + 1)
    if x0 >= x1 or y0 >= y1:
        return outer
    sub, dx, dy = img[y0:y1, x0:x1], v.xx[y0:y1, x0:x1] - c[0], v.yy[y0:y1, x0:x1] - c[1]

    def gap(ex: F32, ey: F32) -> F32:
        """Distance outside the outline seen from above, the washer's or the hexagon's."""
        return cast(F32, np.hypot(ex, ey) - rw if washer else hex_distance(ex, ey, phi) - flats / 2)

    penumbra = 0.15 * flats + 1  # soft edge of the cast shadow
    shadow = np.clip(0.5 - gap(dx + throw[0], dy + throw[1]) / penumbra, 0, 1)
    sub *= 1 - r.uniform(0.25, 0.55) * shadow
    sub *= 1 - r.uniform(0.3, 0.6) * np.exp(-0.5 * (gap(dx, dy) / (0.3 * s + 0.5)) ** 2)
    hid = v.hidden[y0:y1, x0:x1]
    np.maximum(hid, np.clip(0.5 - gap(dx, dy), 0, 1), out=hid)
    dist, tilt = np.hypot(dx, dy), dx * v.light[0] + dy * v.light[1]
    if washer:
        disc = np.clip(rw - dist + 0.5, 0, 1)
        face = r.uniform(80, 190) + 8 * tilt / rw + 3 * smooth_noise(r, sub.shape, 0.2 * s)
        sub[:] = sub * (1 - disc) + disc * face
    if hexagon:
        hx = hex_distance(dx, dy, phi)
        head, edge = np.clip(flats / 2 - hx + 0.5, 0, 1), hx - flats / 2
        chamfer = np.clip((dist - 0.47 * flats) / (0.04 * flats), 0, 1)
        top = r.uniform(70, 200) + 10 * tilt / rh - 30 * chamfer
    else:
        head, edge = np.clip(rh - dist + 0.5, 0, 1), dist - rh
        top = r.uniform(70, 180) + 40 * tilt / rh + 30 * np.exp(-((dist / rh) ** 2) * 4)
    if washer:
        sub *= 1 - 0.4 * np.exp(-0.5 * (edge / (0.3 * s + 0.5)) ** 2)
    sub[:] = sub * (1 - head) + head * (top + 4 * smooth_noise(r, sub.shape, 1.5 * s))
    return outer


def rust_streaks(img: F32, v: View) -> None:
    """Rust streaks: dark smeared trails running down (along gravity) from a source."""
    r, g, sink = v.rng, v.down, np.zeros(v.shape, np.uint8)
    q = np.array([-g[1], g[0]])
    for _ in range(int(r.integers(1, 5))):
        o, width, length = spot(v), r.uniform(1, 8) * v.s, r.uniform(10, 80) * v.s
        for _ in range(12):
            a = o + q * r.normal(0, width / 3)
            b = a + g * length * r.uniform(0.3, 1) + q * r.normal(0, width / 4)
            tone, thick = int(r.integers(15, 45)), max(1, int(width / 5))
            cv2.line(sink, fixed_point(a), fixed_point(b), tone, thick, cv2.LINE_AA, 4)
    img -= blur(sink.astype(np.float32), 0.6 * v.s + 0.5)


def paint_runs(img: F32, v: View) -> None:
    """Paint runs: elongated teardrops along gravity, widening to a bulb at the bottom, shaded."""
    r, g, height = v.rng, v.down, np.zeros(v.shape, np.float32)
    q, tt = np.array([-g[1], g[0]]), np.linspace(0, 1, 12)[:, None]
    for _ in range(int(r.integers(1, 6))):
        top, length, wd = spot(v), r.uniform(5, 40) * v.s, r.uniform(0.8, 3) * v.s
        axis, side = top + tt * length * g, (wd / 2) * (0.25 + 0.75 * tt**1.5) * q
        poly = np.rint(np.vstack([axis + side, (axis - side)[::-1]]) * 16).astype(np.int32)
        cv2.fillPoly(height, [poly], 1.0, cv2.LINE_8, 4)
        cv2.circle(
            height, fixed_point(top + length * g), int(wd * 0.6 * 16), 1.0, -1, cv2.LINE_8, 4
        )
    height = blur(height, 0.3 * v.s + 0.5)
    img += r.uniform(15, 35) * relief(height, v.light) + r.uniform(-6, 6) * height


def scratches(img: F32, v: View) -> None:
    """Short thin scratches, straight or arcs: most bright (through the paint), some dark."""
    r, lift, sink = v.rng, np.zeros(v.shape, np.uint8), np.zeros(v.shape, np.uint8)
    for _ in range(int(r.integers(1, 10))):
        bright = r.random() < 0.7
        canvas, tone = (lift, int(r.integers(15, 60))) if bright else (sink, int(r.integers(8, 30)))
        c, length, a = spot(v), log_uniform(r, 2, 25) * v.s, r.uniform(0, 360)
        thick = max(1, int(round(r.uniform(0.05, 0.3) * v.s)))
        if r.random() < 0.3:
            arc = r.uniform(20, 90)
            rad = int(length / np.radians(arc) * 16)
            cv2.ellipse(canvas, fixed_point(c), (rad, rad), a, 0, arc, tone, thick, cv2.LINE_AA, 4)
        else:
            end = c + length * unit(np.radians(a))
            cv2.line(canvas, fixed_point(c), fixed_point(end), tone, thick, cv2.LINE_AA, 4)
    img += lift.astype(np.float32) - sink
