"""Coverage of the inspected surface: which part the camera imaged well enough to count,
and where the holes are.

A frame counts when its resolution meets the required one (mm per pixel, from the camera's
calibration), it is sharp compared with the session's other frames, and it is exposed
(its brightest pixels are not all dark). The surface "in view" is the surface a sensor saw
within the convex hull of every frame's footprint (or a declared surface outline): the
frames' parts that are not dark (the camera's exposure is set for the lit surface at its
focus distance: past a plate's edge it sees dark), and where the depth camera saw the plane
the robot stands on (:mod:`processing.surface_evidence`); without depth, the whole hull
less what only dark parts of frames showed. A hole is a connected part of it that no
counting frame imaged. Pure functions: arrays and dataclasses in and out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.poses import image_to_world


@dataclass(frozen=True)
class CoverageParams:
    """How coverage is judged (no number here is tied to one camera or structure)."""

    required_mm_per_px: float = 0.3  # finest detail the inspection must resolve
    min_sharpness_ratio: float = 0.35  # of the session's median frame sharpness
    min_frames_for_sharpness: int = 5  # fewer frames: no median to compare with
    dark_level: int = 64  # a frame whose 95th-percentile grey is below this is too dark
    cells_per_footprint: int = 40  # grid cell: the footprint's shorter side over this
    # a hole worth listing is this share of the footprint's shorter side across at its
    # widest (a sliver between two footprints is none)
    min_hole_width: float = 0.25


@dataclass(frozen=True)
class FrameQuality:
    """Sharpness (variance of the Laplacian, grey levels²) and exposure of one frame, and
    the exposure of each of its tiles (a part of the frame past a plate's edge is dark: the
    camera's exposure is set for the lit surface at its focus distance)."""

    sharpness: float
    bright_level: float  # 95th percentile of grey
    tile_bright: NDArray[np.uint8] | None = None  # (rows, cols) each tile's 95th percentile


@dataclass(frozen=True)
class Hole:
    """A part of the surface no counting frame imaged (metres, world frame)."""

    x_m: float  # the point of the hole farthest from anything imaged
    y_m: float
    bbox_m: tuple[float, float, float, float]  # x, y, w, h
    area_m2: float
    centroid_m: tuple[float, float] = (0.0, 0.0)  # may lie outside the hole (a C-shape)


@dataclass(frozen=True)
class SurfaceVotes:
    """Evidence about where the surface is, in the world frame (metres): at each point,
    whether a sensor saw the surface there, and how much that counts."""

    xy: NDArray[np.floating]  # (N, 2)
    on: NDArray[np.bool_]  # (N,)
    weight: NDArray[np.floating]  # (N,)


@dataclass
class Coverage:
    """The coverage grid and what it says."""

    origin_m: tuple[float, float]  # world (x, y) of cell (0, 0)'s corner
    cell_m: float
    imaged: NDArray[np.bool_]  # (rows, cols): imaged by a counting frame
    surface: NDArray[np.bool_]  # (rows, cols): the surface in view
    holes: list[Hole] = field(default_factory=list)

    @property
    def area_imaged_m2(self) -> float:
        return float((self.imaged & self.surface).sum()) * self.cell_m**2

    @property
    def area_surface_m2(self) -> float:
        return float(self.surface.sum()) * self.cell_m**2

    @property
    def fraction(self) -> float:
        return self.area_imaged_m2 / self.area_surface_m2 if self.surface.any() else 0.0


def frame_quality(gray: NDArray[np.uint8], tiles_across: int = 48) -> FrameQuality:
    """Sharpness and exposure of a grey image (H, W) uint8, and the exposure of its tiles
    (``tiles_across`` on its short side, square)."""
    sharp = float(cv2.Laplacian(gray, cv2.CV_32F).var())
    h, w = gray.shape
    side = max(1, min(h, w) // max(tiles_across, 1))
    rows, cols = max(1, h // side), max(1, w // side)
    th, tw = h // rows, w // cols
    blocks = gray[: rows * th, : cols * tw].reshape(rows, th, cols, tw).transpose(0, 2, 1, 3)
    tiles = np.percentile(blocks.reshape(rows, cols, -1), 95, axis=2)
    return FrameQuality(sharp, float(np.percentile(gray, 95)), tiles.astype(np.uint8))


def dark_tiles(quality: FrameQuality | None, params: CoverageParams) -> NDArray[np.bool_] | None:
    """(rows, cols) the tiles of a frame too dark to show the surface, or None (none)."""
    if quality is None or quality.tile_bright is None:
        return None
    dark = np.asarray(quality.tile_bright < params.dark_level)
    return dark if dark.any() else None


def frame_verdicts(
    qualities: Sequence[FrameQuality | None], mm_per_px: float | None, params: CoverageParams
) -> list[str]:
    """Per frame: "" when it counts, else why not (unreadable, too coarse, blurred, dark)."""
    if mm_per_px is None:
        return ["no camera scale in the calibration"] * len(qualities)
    if mm_per_px > params.required_mm_per_px:
        coarse = f"{mm_per_px:.2f} mm/px is coarser than the required {params.required_mm_per_px:g}"
        return [coarse] * len(qualities)
    sharp = [q.sharpness for q in qualities if q is not None]
    median = float(np.median(sharp)) if len(sharp) >= params.min_frames_for_sharpness else 0.0
    out = []
    for q in qualities:
        if q is None:
            out.append("unreadable")
        elif q.bright_level < params.dark_level:
            out.append("too dark")
        elif q.sharpness < params.min_sharpness_ratio * median:
            out.append("blurred")
        else:
            out.append("")
    return out


def footprint(
    camera_pose: NDArray[np.floating], px_per_m: float, size: tuple[int, int]
) -> NDArray[np.float64]:
    """World corners (4, 2) of a downward-camera image of ``size`` (w, h) at ``camera_pose``."""
    w, h = size
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=np.float64) - 0.5
    return image_to_world(corners, camera_pose, px_per_m, size)


def coverage_map(
    footprints: Sequence[NDArray[np.floating]],
    counts: Sequence[bool],
    params: CoverageParams = CoverageParams(),
    surface_outline: NDArray[np.floating] | None = None,
    surface_votes: SurfaceVotes | None = None,
    dark: Sequence[NDArray[np.bool_] | None] | None = None,
) -> Coverage:
    """Rasterise the footprints (each (4, 2) metres) of the frames that count onto a grid
    over the surface in view and find the holes.

    ``dark``, per frame, which of its tiles (rows, cols, over the image as its footprint's
    corners order it) are too dark to show the surface, or None; a frame's dark tiles
    image nothing. The surface in view lies within ``surface_outline`` (N, 2), else the
    hull of all footprints; with ``surface_votes`` (what a depth camera saw) it is what a
    frame's bright tiles showed (counting or not) or the votes say is surface (more weight
    for it than against), and without them, the whole hull less what only dark tiles
    showed."""
    if not len(footprints):
        empty = np.zeros((0, 0), bool)
        return Coverage((0.0, 0.0), 1.0, empty, empty)
    polys = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in footprints]
    short = min(float(np.linalg.norm(p[1] - p[0])) for p in polys)
    short = min(short, min(float(np.linalg.norm(p[2] - p[1])) for p in polys))
    cell = max(short, 1e-6) / params.cells_per_footprint
    every = np.vstack(
        polys + ([np.asarray(surface_outline)] if surface_outline is not None else [])
    )
    lo = every.min(axis=0) - cell
    cols, rows = (np.ceil((every.max(axis=0) + cell - lo) / cell).astype(int) + 1).tolist()

    def cells(p: NDArray[np.float64]) -> NDArray[np.int32]:
        return np.round((p - lo) / cell - 0.5).astype(np.int32).reshape(-1, 1, 2)

    imaged = np.zeros((rows, cols), np.uint8)  # by the frames that count
    seen = np.zeros((rows, cols), np.uint8)  # by the others: the surface is there
    dark_cells = np.zeros((rows, cols), np.uint8)
    for p, ok, d in zip(polys, counts, dark if dark is not None else [None] * len(polys)):
        into = imaged if ok else seen
        if d is None:  # one at a time: fillPoly XORs overlapping contours
            cv2.fillPoly(into, [cells(p)], 1)
        else:
            _paint_tiles(into, dark_cells, (p - lo) / cell - 0.5, np.asarray(d, bool))
    seen |= imaged
    surface = np.zeros_like(imaged)
    if surface_outline is not None:
        outline = cells(np.asarray(surface_outline, dtype=np.float64))
    else:  # the hull of the footprints' own corner cells: its edges rasterise as theirs do
        outline = cast(NDArray[np.int32], cv2.convexHull(np.vstack([cells(p) for p in polys])))
    cv2.fillPoly(surface, [outline], 1)
    if surface_votes is not None:  # in view: what the camera or the depth camera saw
        against, for_ = _surface_votes(surface_votes, lo, cell, surface.shape)
        surface &= (seen > 0) | (for_ > against)
    else:  # in view: the hull, less what only the dark parts of frames showed
        surface[(dark_cells > 0) & (seen == 0)] = 0
    result = Coverage((float(lo[0]), float(lo[1])), cell, imaged.astype(bool), surface.astype(bool))
    result.holes = find_holes(
        result,
        min_cells=params.cells_per_footprint // 4,
        min_width_cells=params.min_hole_width * params.cells_per_footprint,
    )
    return result


def _paint_tiles(
    bright: NDArray[np.uint8],
    dark: NDArray[np.uint8],
    corners: NDArray[np.float64],
    is_dark: NDArray[np.bool_],
) -> None:
    """Mark the grid cells whose centres fall in a frame's bright tiles in ``bright`` and in
    its dark tiles in ``dark``; ``corners`` (4, 2) the footprint's corners in cell units."""
    rows, cols = is_dark.shape
    p0 = corners[0]
    ex, ey = (corners[1] - p0) / cols, (corners[3] - p0) / rows
    # tile units (a, b) -> cells: p0 + a·ex + b·ey, over the cells the footprint spans
    x0, y0 = np.floor(corners.min(axis=0)).astype(int)
    x1, y1 = np.ceil(corners.max(axis=0)).astype(int) + 1
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, bright.shape[1]), min(y1, bright.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    # OpenCV's tile (i, j) is centred at (i, j), tile units (i + 0.5, j + 0.5); each cell
    # centre (whole numbers in these cell units) looks up the tile it falls in
    M = np.column_stack([ex, ey, p0 + 0.5 * (ex + ey) - (x0, y0)])
    states = np.where(is_dark, 2, 1).astype(np.uint8)
    out = cv2.warpAffine(
        states, M, (x1 - x0, y1 - y0), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE
    )
    # the footprint's cells as a whole footprint is filled (its border cells included)
    inside = np.zeros_like(out)
    poly = np.round(corners - (x0, y0)).astype(np.int32).reshape(-1, 1, 2)
    cv2.fillPoly(inside, [poly], 1)
    out[inside == 0] = 0
    bright[y0:y1, x0:x1] |= (out == 1).astype(np.uint8)
    dark[y0:y1, x0:x1] |= (out == 2).astype(np.uint8)


def _surface_votes(
    votes: SurfaceVotes, lo: NDArray[np.float64], cell: float, shape: tuple[int, ...]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(rows, cols) the weight of the votes against the surface in each cell, and for it."""
    rows, cols = shape
    c = np.floor((np.asarray(votes.xy, np.float64) - lo) / cell).astype(np.int64)
    inside = (c[:, 0] >= 0) & (c[:, 0] < cols) & (c[:, 1] >= 0) & (c[:, 1] < rows)
    idx = c[inside, 1] * cols + c[inside, 0]
    w = np.asarray(votes.weight, np.float64)[inside]
    on = np.asarray(votes.on, bool)[inside]
    for_ = np.bincount(idx[on], w[on], rows * cols).astype(np.float64).reshape(rows, cols)
    against = np.bincount(idx[~on], w[~on], rows * cols).astype(np.float64).reshape(rows, cols)
    return against, for_


def hole_mask(cov: Coverage) -> NDArray[np.bool_]:
    """(rows, cols) the surface not imaged."""
    return cov.surface & ~cov.imaged


def find_holes(cov: Coverage, min_cells: int = 1, min_width_cells: float = 0.0) -> list[Hole]:
    """Connected parts of the surface not imaged, largest first: each at least
    ``min_cells`` cells and ``min_width_cells`` across at its widest (the diameter of the
    largest disc it holds: a sliver between two footprints is no hole), placed at that
    disc's centre, the point of the hole farthest from anything imaged (a C-shaped hole's
    centroid can lie in the lane it wraps)."""
    mask = hole_mask(cov).astype(np.uint8)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=4)
    # distance of each hole cell to the nearest cell that is not hole (padded: the grid's
    # edge is no hole's border)
    inside = cv2.distanceTransform(
        cv2.copyMakeBorder(mask, 1, 1, 1, 1, cv2.BORDER_REPLICATE), cv2.DIST_L2, 5
    )[1:-1, 1:-1]
    ox, oy = cov.origin_m
    holes = []
    for i in range(1, n):
        x, y, w, h, area = stats[i]
        if area < max(min_cells, 1):
            continue
        here = np.where(labels[y : y + h, x : x + w] == i, inside[y : y + h, x : x + w], 0)
        r, c = np.unravel_index(int(np.argmax(here)), here.shape)
        if 2 * float(here[r, c]) < min_width_cells:
            continue
        holes.append(
            Hole(
                ox + (x + c + 0.5) * cov.cell_m,
                oy + (y + r + 0.5) * cov.cell_m,
                (ox + x * cov.cell_m, oy + y * cov.cell_m, w * cov.cell_m, h * cov.cell_m),
                float(area) * cov.cell_m**2,
                (
                    ox + (centroids[i][0] + 0.5) * cov.cell_m,
                    oy + (centroids[i][1] + 0.5) * cov.cell_m,
                ),
            )
        )
    return sorted(holes, key=lambda h: -h.area_m2)
