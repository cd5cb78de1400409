"""Defect detection on mosaics of any size with bounded memory.

The mosaic PNG is unpacked by libvips into a raw scratch file; each band (with ``overlap``
rows of context above and below) is an independent part whose masks are computed in memory
and whose core rows are written to raw band files (crack mask, rust mask, crack contrast).
The band files are then read in order: components are labelled per band and joined across
band seams, ``crack_mask.png`` and ``corrosion_mask.png`` are streamed from them, and each
joined defect is measured on a crop of them, so a defect that crosses a seam is measured
whole, exactly as in one pass. Every scratch file is written behind
(:mod:`server.storage.write_behind`): a job's hundreds of megabytes do not stall the live
link's writes on the same disk.
"""

from __future__ import annotations

import functools
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyvips
from numpy.typing import NDArray
from scipy.cluster.hierarchy import DisjointSet

from processing.defects import Defect, measure_defects, moved, seam_links
from processing.detection import DefectMasks
from processing.surface import on_surface
from server.storage.files import write_atomic
from server.storage.write_behind import save_behind

CLASSES = ("crack", "corrosion")
Masks = Callable[[NDArray[np.uint8], NDArray[np.bool_], NDArray[np.bool_] | None], DefectMasks]


@dataclass
class _Part:
    """A component of one band: its global box and a pixel of it."""

    x0: int
    y0: int
    x1: int
    y1: int
    seed: tuple[int, int]


@dataclass
class _Parts:
    """Every band's components of one class, and which touch across seams."""

    parts: dict[tuple[int, int], _Part] = field(default_factory=dict)  # (band, label) -> part
    links: list[tuple[tuple[int, int], tuple[int, int]]] = field(default_factory=list)
    last_row: NDArray[np.int32] | None = None


def _unpack(png: Path, raw: Path, bands: int) -> None:
    """A PNG's first ``bands`` channels as a raw (H, W, bands) uint8 file, streamed by
    libvips top to bottom (bounded memory), for bands to be read from anywhere."""
    img = pyvips.Image.new_from_file(str(png), access="sequential")
    if img.bands > bands:
        img = img.extract_band(0, n=bands)
    save_behind(img.cast("uchar"), raw, ".raw")


@dataclass(frozen=True)
class BandPlan:
    """What every band's part shares: the unpacked mosaic in ``scratch`` and how to search it."""

    scratch: str
    width: int
    height: int
    overlap: int
    level: float
    masks: Masks
    have_seams: bool


MapBands = Callable[[Callable[..., None], BandPlan, list[tuple[int, tuple[int, int]]]], list[None]]


def _serial(fn: Callable[..., None], plan: BandPlan, items: list[Any]) -> list[None]:
    return [fn(None, plan, item) for item in items]


def band_masks(_files: object, plan: BandPlan, band: tuple[int, tuple[int, int]]) -> None:
    """One band's crack, corrosion and contrast core rows, computed with ``overlap`` rows of
    context above and below, written beside the plan (a part: any worker may run it)."""
    index, (y0, y1) = band
    scratch, w, h = Path(plan.scratch), plan.width, plan.height
    a0, a1 = max(0, y0 - plan.overlap), min(h, y1 + plan.overlap)

    def rows(name: str, bands: int) -> NDArray[np.uint8]:
        shape = (h, w, bands) if bands > 1 else (h, w)
        return np.array(np.memmap(scratch / name, dtype=np.uint8, mode="r", shape=shape)[a0:a1])

    image = cv2.cvtColor(rows("image.raw", 3), cv2.COLOR_RGB2BGR)  # OpenCV's channel order
    coverage = rows("coverage.raw", 1)
    seams = rows("seams.raw", 1) > 0 if plan.have_seams else None
    found = plan.masks(image, on_surface(image, coverage, plan.level), seams)
    a, b = y0 - a0, y1 - a0
    contrast = np.clip(np.round(np.where(found.cracks[a:b], found.contrast[a:b], 0)), 0, 255)
    for name, part in (
        ("crack", found.cracks[a:b]),
        ("corrosion", found.rust[a:b]),
        ("contrast", contrast),
    ):
        write_atomic(scratch / f"band{index}.{name}", part.astype(np.uint8).tobytes())


BUDGET_BYTES = 768 * 2**20  # a band's working set, context rows included
MIN_BAND_ROWS = 128  # twice the context rows: thinner bands would mostly repeat context
BYTES_PER_PX = 96  # measured: the detectors' intermediates per pixel of a band


def band_rows(
    width: int, overlap: int, budget_bytes: int = BUDGET_BYTES, per_px: int = BYTES_PER_PX
) -> int:
    """Core rows per band so that a band with its context rows fits the memory budget."""
    return int(max(MIN_BAND_ROWS, budget_bytes // max(1, width * per_px) - 2 * overlap))


def detect_banded(
    results: Path,
    out: Path,
    masks: Masks,
    mm_per_px: float | None,
    level: float,
    *,
    rows: int | None = None,
    overlap: int = 64,
    progress: Callable[[float, str], None] = lambda f, m: None,
    map_bands: MapBands = _serial,
    parallel: int = 1,
    min_bands: int = 1,
) -> list[Defect]:
    """Cracks and corrosion of ``results/mosaic.png`` (with its coverage and seams), band by
    band; writes the two mask PNGs into ``out`` (its scratch files too) and returns the
    measured defects (mosaic pixels).

    The mosaic is unpacked once into a raw scratch file; the bands are independent parts
    (``map_bands``: in turn, on threads, or on other workers; ``parallel`` of them at once
    share the memory budget; at least ``min_bands`` of them, for workers to share); their
    masks are then labelled in order, joined across seams, and measured."""
    header = pyvips.Image.new_from_file(str(results / "mosaic.png"))
    width, height = header.width, header.height
    rows = rows or min(
        band_rows(width, overlap, BUDGET_BYTES // max(1, parallel)),
        max(MIN_BAND_ROWS, -(-height // max(1, min_bands))),
    )
    scratch = out / ".detect-scratch"
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir()
    try:
        have_seams = (results / "mosaic_seams.png").is_file()
        _unpack(results / "mosaic.png", scratch / "image.raw", 3)
        _unpack(results / "mosaic_coverage.png", scratch / "coverage.raw", 1)
        if have_seams:
            _unpack(results / "mosaic_seams.png", scratch / "seams.raw", 1)
        progress(0.1, "mosaic unpacked")
        cores = [(y, min(y + rows, height)) for y in range(0, height, rows)]
        plan = BandPlan(str(scratch), width, height, overlap, level, masks, have_seams)
        map_bands(band_masks, plan, list(enumerate(cores)))
        progress(0.8, f"{len(cores)} bands searched")
        maps = {n: _Joined(scratch, n, cores, width) for n in ("crack", "corrosion", "contrast")}
        parts = {c: _Parts() for c in CLASSES}
        for band, (y0, _) in enumerate(cores):
            for name in CLASSES:
                _label(parts[name], maps[name].band(band) > 0, band, y0)
        progress(0.9, "bands joined")
        for name, file in (("crack", "crack_mask.png"), ("corrosion", "corrosion_mask.png")):
            _save_mask(maps[name].vips(), out / file)
        found: list[Defect] = []
        for name in CLASSES:
            found += _measure(
                parts[name],
                maps[name],
                maps["contrast"] if name == "crack" else None,
                name,
                mm_per_px,
                len(found) + 1,
            )
        return found
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


class _Joined:
    """One of the bands' outputs (crack, corrosion or contrast) joined into the mosaic's
    rows without a copy: read by slices, by band, or streamed by libvips from the band files."""

    def __init__(self, scratch: Path, name: str, cores: list[tuple[int, int]], width: int):
        self.files = [scratch / f"band{k}.{name}" for k in range(len(cores))]
        self.cores, self.width = cores, width
        self.shape = (cores[-1][1] if cores else 0, width)

    def band(self, k: int) -> NDArray[np.uint8]:
        """Band ``k``'s core rows, shape (rows, W)."""
        y0, y1 = self.cores[k]
        return np.fromfile(self.files[k], dtype=np.uint8).reshape(y1 - y0, self.width)

    def __getitem__(self, key: tuple[slice, slice]) -> NDArray[np.uint8]:
        """Rows ``ys`` and columns ``xs`` of the joined mosaic (plain slices)."""
        ys, xs = key
        y_lo, y_hi, _ = ys.indices(self.shape[0])
        pieces = []
        for path, (y0, y1) in zip(self.files, self.cores):
            a, b = max(y_lo, y0), min(y_hi, y1)
            if a < b:
                rows = np.memmap(path, dtype=np.uint8, mode="r", shape=(y1 - y0, self.width))
                pieces.append(np.array(rows[a - y0 : b - y0, xs]))
        return np.concatenate(pieces) if pieces else np.zeros((0, 0), np.uint8)

    def vips(self) -> pyvips.Image:
        """The whole mask as one libvips image, (H, W), read band file by band file."""
        rows = [
            pyvips.Image.rawload(str(path), self.width, y1 - y0, 1)
            for path, (y0, y1) in zip(self.files, self.cores)
        ]
        return functools.reduce(lambda top, below: top.join(below, "vertical"), rows)


def _label(acc: _Parts, mask: NDArray[np.bool_], band: int, y0: int) -> None:
    """Record a band's components and link them to those of the band above."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n > 1:
        ys, xs = np.nonzero(labels)
        first = np.unique(labels[ys, xs], return_index=True)
        for lab, idx in zip(first[0].tolist(), first[1].tolist()):
            x, y, w, h = (int(v) for v in stats[lab][:4])
            acc.parts[(band, lab)] = _Part(
                x, y0 + y, x + w, y0 + y + h, (int(xs[idx]), int(ys[idx]) + y0)
            )
    if acc.last_row is not None and len(labels):
        acc.links += [((band - 1, a), (band, b)) for a, b in seam_links(acc.last_row, labels[0])]
    acc.last_row = labels[-1].copy() if len(labels) else None


def _measure(
    acc: _Parts,
    mask: _Joined,
    contrast: _Joined | None,
    name: str,
    mm_per_px: float | None,
    first_id: int,
) -> list[Defect]:
    """Each joined component measured on a crop around it."""
    groups = DisjointSet(list(acc.parts))
    for a, b in acc.links:
        if a in acc.parts and b in acc.parts:
            groups.merge(a, b)
    found: list[Defect] = []
    for members in groups.subsets():
        ps = [acc.parts[m] for m in members]
        x0, y0 = max(0, min(p.x0 for p in ps) - 2), max(0, min(p.y0 for p in ps) - 2)
        x1, y1 = (
            min(mask.shape[1], max(p.x1 for p in ps) + 2),
            min(mask.shape[0], max(p.y1 for p in ps) + 2),
        )
        crop = np.asarray(mask[y0:y1, x0:x1]) > 0
        _, labels = cv2.connectedComponents(crop.astype(np.uint8), connectivity=8)
        sx, sy = ps[0].seed
        one = labels == labels[sy - y0, sx - x0]
        c = np.asarray(contrast[y0:y1, x0:x1], dtype=np.float32) if contrast is not None else None
        for d in measure_defects(one, name, mm_per_px=mm_per_px, contrast=c):
            found.append(moved(d, x0, y0, first_id + len(found)))
    found.sort(key=lambda d: (d.bbox[1], d.bbox[0]))
    return [moved(d, 0, 0, first_id + i) for i, d in enumerate(found)]


def _save_mask(mask: pyvips.Image, out: Path) -> None:
    """A 0/1 mask as a 0/255 PNG, streamed by libvips, written atomically."""
    tmp = out.with_name(f".{out.name}.tmp.png")
    save_behind((mask.copy(interpretation="b-w") * 255).cast("uchar"), tmp, ".png", compression=3)
    tmp.replace(out)
