"""Defect detection on mosaics of any size with bounded memory.

The mosaic PNG is read top to bottom by libvips in bands (each with ``overlap`` rows of
context above and below); a band's masks are computed in memory and its core rows written
to raw scratch files (crack mask, rust mask, crack contrast), which are then streamed into
``crack_mask.png`` and ``corrosion_mask.png``. Components are labelled per band and joined
across band seams; each joined defect is then measured on a crop of the scratch files
(memory-mapped), so a defect that crosses a seam is measured whole, exactly as in one pass.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pyvips
from numpy.typing import NDArray
from scipy.cluster.hierarchy import DisjointSet

from processing.defects import Defect, measure_defects, moved, seam_links
from processing.detection import DefectMasks
from processing.surface import on_surface

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


def _rows(path: Path, bands: int, rows: int) -> Iterator[NDArray[np.uint8]]:
    """The image at ``path`` in successive blocks of ``rows`` rows. libvips decodes a PNG
    once for random access: into memory when small, into a temporary file on disk when
    large (beyond its disc threshold, 100 MB by default), so memory stays bounded."""
    img = pyvips.Image.new_from_file(str(path), access="random")
    if img.bands > bands:
        img = img.extract_band(0, n=bands)
    for y in range(0, img.height, rows):
        h = min(rows, img.height - y)
        block = np.ndarray(
            buffer=img.crop(0, y, img.width, h).write_to_memory(),
            dtype=np.uint8,
            shape=(h, img.width, img.bands),
        )
        yield (
            cv2.cvtColor(block, cv2.COLOR_RGB2BGR) if bands == 3 else block[..., 0]
        )  # OpenCV's channel order


BUDGET_BYTES = 768 * 2**20  # a band's working set, context rows included
BYTES_PER_PX = 96  # measured: the detectors' intermediates per pixel of a band


def band_rows(
    width: int, overlap: int, budget_bytes: int = BUDGET_BYTES, per_px: int = BYTES_PER_PX
) -> int:
    """Core rows per band so that a band with its context rows fits the memory budget."""
    return int(max(128, budget_bytes // max(1, width * per_px) - 2 * overlap))


def detect_banded(
    results: Path,
    masks: Masks,
    mm_per_px: float | None,
    level: float,
    *,
    rows: int | None = None,
    overlap: int = 64,
    progress: Callable[[float, str], None] = lambda f, m: None,
) -> list[Defect]:
    """Cracks and corrosion of ``results/mosaic.png`` (with its coverage and seams), band by
    band; writes the two mask PNGs and returns the measured defects (mosaic pixels)."""
    header = pyvips.Image.new_from_file(str(results / "mosaic.png"))
    width, height = header.width, header.height
    rows = rows or band_rows(width, overlap)
    scratch = results / ".detect-scratch"
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir()
    try:
        maps = {
            name: np.memmap(
                scratch / f"{name}.raw", mode="w+", dtype=np.uint8, shape=(height, width)
            )
            for name in ("crack", "corrosion", "contrast")
        }
        parts = {c: _Parts() for c in CLASSES}
        have_seams = (results / "mosaic_seams.png").is_file()
        streams = [
            _rows(results / "mosaic.png", 3, rows),
            _rows(results / "mosaic_coverage.png", 1, rows),
        ]
        if have_seams:
            streams.append(_rows(results / "mosaic_seams.png", 1, rows))
        buffers: list[NDArray[np.uint8] | None] = [None] * len(streams)
        buf_y0, core_y0, band = 0, 0, 0
        exhausted = False
        while core_y0 < height:
            core_y1 = min(core_y0 + rows, height)
            # read until the buffer reaches past the core's context (or the image ends)
            while not exhausted and (
                buffers[0] is None or buf_y0 + len(buffers[0]) < min(core_y1 + overlap, height)
            ):
                blocks = [next(s, None) for s in streams]
                if blocks[0] is None:
                    exhausted = True
                    break
                buffers = [
                    b if buf is None else np.concatenate([buf, b])
                    for buf, b in zip(buffers, blocks)
                ]  # type: ignore[list-item]
            image, coverage = buffers[0], buffers[1]
            seams = buffers[2] > 0 if have_seams else None
            assert image is not None and coverage is not None
            found_in = masks(image, on_surface(image, coverage, level), seams)
            cracks, rust, contrast = found_in.cracks, found_in.rust, found_in.contrast
            a, b = core_y0 - buf_y0, core_y1 - buf_y0
            maps["crack"][core_y0:core_y1] = cracks[a:b]
            maps["corrosion"][core_y0:core_y1] = rust[a:b]
            maps["contrast"][core_y0:core_y1] = np.clip(
                np.round(np.where(cracks[a:b], contrast[a:b], 0)), 0, 255
            )
            for name, mask in (("crack", cracks[a:b]), ("corrosion", rust[a:b])):
                _label(parts[name], mask, band, core_y0)
            progress(core_y1 / height, f"mosaic rows {core_y1}/{height}")
            # keep only the context the next core needs
            core_y0, band = core_y1, band + 1
            drop = max(0, (core_y0 - overlap) - buf_y0)
            buffers = [buf[drop:] if buf is not None else None for buf in buffers]
            buf_y0 += drop
        for name, out in (("crack", "crack_mask.png"), ("corrosion", "corrosion_mask.png")):
            maps[name].flush()
            _save_mask(scratch / f"{name}.raw", results / out, width, height)
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
    mask: NDArray[np.uint8],
    contrast: NDArray[np.uint8] | None,
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


def _save_mask(raw: Path, out: Path, width: int, height: int) -> None:
    """A 0/1 raw scratch mask as a 0/255 PNG, streamed by libvips, written atomically."""
    img = pyvips.Image.rawload(str(raw), width, height, 1).copy(interpretation="b-w")
    tmp = out.with_name(f".{out.name}.tmp.png")
    (img * 255).cast("uchar").pngsave(str(tmp), compression=3)
    tmp.replace(out)
