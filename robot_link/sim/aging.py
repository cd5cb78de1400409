"""The same simulated structure visited again months later: cracks extended at a tip and
some widened, rust patches grown and new ones, the paint weathered and the light different, with the true
growth of each defect known."""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from skimage.morphology import skeletonize

from robot_link.sim.structure import (
    SteelStructure,
    TrueDefect,
    _draw_corrosion,
    _draw_crack,
    _noise,
    _true_defect,
)


@dataclass(frozen=True)
class Growth:
    """What happened to one defect between the visits (metres, m²)."""

    defect_id: int
    defect_class: str
    length_m: float = 0.0  # added to a crack
    width_m: float = 0.0  # added to a crack's width
    area_m2: float = 0.0  # added to a rust patch
    new: bool = False


def _tip(skel: NDArray[np.bool_]) -> tuple[NDArray[np.float64], float] | None:
    """An end of a crack's skeleton and the heading pointing out of it."""
    ys, xs = np.nonzero(skel)
    if len(xs) < 3:
        return None
    pts = np.stack([xs, ys], 1).astype(np.float64)
    far = pts[np.argmax(np.linalg.norm(pts - pts.mean(0), axis=1))]  # one end
    near = pts[np.linalg.norm(pts - far, axis=1) < 12]
    direction = far - near.mean(0)
    if not np.any(direction):
        return None
    return far, float(np.arctan2(direction[1], direction[0]))


def _widen(
    img: NDArray[np.float32], crack_mask: NDArray[np.uint8], mine: NDArray[np.bool_]
) -> NDArray[np.bool_]:
    """A crack's pixels (``mine``) grown by a pixel all round, painted as the crack painter
    paints (0.85 of the crack's dark grey); the wider crack's pixels."""
    ring = cv2.dilate(mine.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~mine
    img[ring] = img[ring] * 0.15 + np.array([38, 36, 34], np.float32) * 0.85
    crack_mask[ring] = 255
    return mine | ring


def _free_spot(
    rng: np.random.Generator, structure: SteelStructure, region_m: tuple[float, float, float, float]
) -> NDArray[np.float64]:
    """A place (m) in ``region_m`` (x0, y0, x1, y1) 0.1 m from every defect's box, or as far
    from them as 200 tries find."""
    x0, y0, x1, y1 = region_m
    best, best_gap = np.array([(x0 + x1) / 2, (y0 + y1) / 2]), -1.0
    for _ in range(200):
        spot = rng.uniform((x0, y0), (x1, y1))
        gap = min(
            (
                float(
                    np.hypot(*np.maximum(0, np.abs(spot - (x + w / 2, y + h / 2)) - (w / 2, h / 2)))
                )
                for x, y, w, h in (d.bbox_m for d in structure.defects)
            ),
            default=1.0,
        )
        if gap >= 0.1:
            return spot
        if gap > best_gap:
            best, best_gap = spot, gap
    return best


def weather(
    image: NDArray[np.float32], rng: np.random.Generator, strength: float
) -> NDArray[np.float32]:
    """Paint faded and the light changed: ``image`` (H, W, 3) times a smooth gain field of
    about ±``strength`` (a plate-wide brighter or darker visit, a shadow, a sunlit side), the
    blue of the paint faded by up to ``strength``, and a finer chalking of the surface."""
    h, w = image.shape[:2]
    level = 1 + strength * rng.uniform(-1, 1)
    gain = level + strength * np.clip(_noise(rng, (h, w), max(h, w) // 3), -1.5, 1.5)
    chalk = 60 * strength * _noise(rng, (h, w), 24)
    out = image * gain[..., None] + chalk[..., None]
    out[..., 0] *= 1 - strength * rng.uniform(0, 1)  # the blue fades first
    return out


def age_structure(
    structure: SteelStructure,
    seed: int,
    crack_growth_m: tuple[float, float] = (0.005, 0.03),
    weathering: float = 0.0,
    region_m: tuple[float, float, float, float] | None = None,
    widen_share: float = 0.5,
) -> tuple[SteelStructure, list[Growth]]:
    """The structure a visit later: each crack longer by ``crack_growth_m`` (a range) at one
    tip and ``widen_share`` of them a pixel wider on each side, each rust patch grown, one new rust patch (in ``region_m``, x0, y0, x1, y1 in metres:
    by default the plate 0.1 m in from its edges), and the surface :func:`weather` ed by
    ``weathering`` (0: as it was); and the truth of each change."""
    rng = np.random.default_rng(seed)
    mpp = structure.m_per_px
    img = structure.texture.astype(np.float32)
    crack = structure.crack_mask.astype(np.uint8) * 255
    rust = structure.corrosion_mask.astype(np.uint8) * 255
    defects: list[TrueDefect] = []
    growth: list[Growth] = []
    for d in structure.defects:
        x, y, w, h = (int(round(v / mpp)) for v in d.bbox_m)
        box = (slice(max(0, y - 2), y + h + 2), slice(max(0, x - 2), x + w + 2))
        if d.defect_class == "crack":
            mine = np.zeros(crack.shape, bool)
            mine[box] = structure.crack_mask[box]
            tip = _tip(skeletonize(mine))
            if tip is None:
                defects.append(d)
                continue
            added = rng.uniform(*crack_growth_m)
            new = _draw_crack(
                rng, img, crack, tip[0], added / mpp, d.width_m / mpp, tip[1], turn_sigma=0.15
            )
            both = mine | new
            wider = 0.0
            if rng.uniform() < widen_share:
                both = _widen(img, crack, both)
                wider = 2 * mpp  # a pixel on each side
            defects.append(
                _true_defect(d.id, "crack", both, mpp, d.length_m + added, d.width_m + wider)
            )
            growth.append(Growth(d.id, "crack", length_m=added, width_m=wider))
        else:
            ys, xs = np.nonzero(structure.corrosion_mask[box])
            centre = np.array([xs.mean() + box[1].start, ys.mean() + box[0].start])
            radius = d.width_m / 2 * rng.uniform(1.1, 1.3) / mpp
            old = np.zeros(rust.shape, bool)
            old[box] = structure.corrosion_mask[box]
            grown = _draw_corrosion(rng, img, rust, centre, radius) | old
            before = int(old.sum())
            d2 = _true_defect(d.id, "corrosion", grown, mpp, 2 * radius * mpp, 2 * radius * mpp)
            defects.append(d2)
            growth.append(Growth(d.id, "corrosion", area_m2=(int(grown.sum()) - before) * mpp**2))
    w_m, h_m = structure.plate_size_m
    spot = _free_spot(rng, structure, region_m or (0.1, 0.1, w_m - 0.1, h_m - 0.1)) / mpp
    radius_m = rng.uniform(0.015, 0.025)
    patch = _draw_corrosion(rng, img, rust, spot, radius_m / mpp)
    new_id = max((d.id for d in defects), default=0) + 1
    defects.append(_true_defect(new_id, "corrosion", patch, mpp, 2 * radius_m, 2 * radius_m))
    growth.append(Growth(new_id, "corrosion", area_m2=float(patch.sum()) * mpp**2, new=True))
    if weathering > 0:
        img = weather(img, rng, weathering)
    aged = replace(
        structure,
        texture=np.clip(img, 0, 255).astype(np.uint8),
        crack_mask=crack > 0,
        corrosion_mask=rust > 0,
        defects=defects,
    )
    return aged, growth
