"""Defect detection on mosaics of any size with bounded memory.

The mosaic PNG, its coverage and seams are first unpacked into raw scratch files, in
pieces that any worker may decode: a PNG joined from segments by the stitcher carries
their index, so each piece is a run of its rows (:func:`server.storage.png_segments.read_rows`);
another tool's PNG is one piece, streamed by libvips. Each band (with ``overlap`` rows of
context above and below) is then an independent part: it reads its rows of the pieces,
computes its masks in memory, labels their components, and writes its core rows to raw
band files (crack mask, rust mask, crack contrast), as segments of the two mask PNGs, and
the components' boxes and edge rows. The bands' components are joined across band seams in
order, the mask PNGs joined from their segments, and each joined defect measured on a crop
of the band files, so a defect that crosses a seam is measured whole, exactly as in one
pass. Every scratch file is written behind (:mod:`server.storage.write_behind`): a job's
hundreds of megabytes do not stall the live link's writes on the same disk.
"""

from __future__ import annotations

import io
import json
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyvips
from numpy.typing import NDArray
from scipy.cluster.hierarchy import DisjointSet

from processing.detection import DefectMasks
from processing.detection.confidence import Calibration, logit_code, probability_of_code
from processing.detection.defects import Components, Defect, measure_defects, moved, seam_links
from processing.detection.surface import on_surface
from server.storage.files import write_atomic
from server.storage.png_segments import join_segments, read_rows, segment_rows, write_segment
from server.storage.write_behind import save_behind, write_file_behind

CLASSES = ("crack", "corrosion")
INPUTS = {
    "image": ("mosaic.png", 3),
    "coverage": ("mosaic_coverage.png", 1),
    "seams": ("mosaic_seams.png", 1),
}  # scratch name: (PNG, channels)
MAX_PIECES = 64  # pieces per input: four chunks each for up to sixteen workers
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
    """Every band's components of one class on its edges, which of them touch across
    seams, and the defects measured inside the bands."""

    parts: dict[tuple[int, int], _Part] = field(default_factory=dict)  # (band, label) -> part
    inner: list[Defect] = field(default_factory=list)  # measured inside their bands
    links: list[tuple[tuple[int, int], tuple[int, int]]] = field(default_factory=list)
    last_row: NDArray[np.int32] | None = None


def _unpack(png: Path, raw: Path, bands: int) -> None:
    """A PNG's first ``bands`` channels as a raw (H, W, bands) uint8 file, streamed by
    libvips top to bottom (bounded memory), for bands to be read from anywhere."""
    img = pyvips.Image.new_from_file(str(png), access="sequential")
    if img.bands > bands:
        img = img.extract_band(0, n=bands)
    save_behind(img.cast("uchar"), raw, ".raw")


def pieces_of(png: Path, height: int) -> list[tuple[int, int]]:
    """Row ranges (y0, y1) a PNG is unpacked in: runs of its segments, at most
    :data:`MAX_PIECES` of them; the whole image for a PNG without a segment index."""
    segments = segment_rows(png)
    if not segments:
        return [(0, height)]
    runs = np.array_split(np.arange(len(segments)), min(len(segments), MAX_PIECES))
    return [(segments[r[0]][0], segments[r[-1]][1]) for r in runs]


@dataclass(frozen=True)
class BandPlan:
    """What every part shares: where the PNGs are (``source``) and are unpacked to
    (``scratch``), in which pieces (input name: row ranges), and how to search them."""

    source: str
    scratch: str
    pieces: dict[str, list[tuple[int, int]]]
    width: int
    height: int
    overlap: int
    level: float
    masks: Masks
    mm_per_px: float | None


MapBands = Callable[[Callable[..., None], BandPlan, list[Any]], list[None]]


def _serial(fn: Callable[..., None], plan: BandPlan, items: list[Any]) -> list[None]:
    return [fn(None, plan, item) for item in items]


def unpack_piece(_files: object, plan: BandPlan, piece: tuple[str, int]) -> None:
    """Piece ``k`` of an input (``piece``: its name and ``k``) as a raw (rows, W[, C]) file in
    the scratch folder (a part: any worker may run it)."""
    name, k = piece
    png, channels = INPUTS[name]
    y0, y1 = plan.pieces[name][k]
    raw = Path(plan.scratch) / f"{name}{k}.raw"
    rows = read_rows(Path(plan.source) / png, y0, y1)
    if rows is None:
        _unpack(Path(plan.source) / png, raw, channels)
    else:
        write_file_behind(raw, rows.data)


def _input(plan: BandPlan, name: str) -> RowFiles:
    files = [Path(plan.scratch) / f"{name}{k}.raw" for k in range(len(plan.pieces[name]))]
    return RowFiles(files, plan.pieces[name], plan.width, INPUTS[name][1])


def band_masks(_files: object, plan: BandPlan, band: tuple[int, tuple[int, int]]) -> None:
    """One band's crack, corrosion and contrast core rows, computed with ``overlap`` rows of
    context above and below, written beside the plan with its components and its rows of
    the mask PNGs (a part: any worker may run it)."""
    index, (y0, y1) = band
    scratch, rows = Path(plan.scratch), slice(max(0, y0 - plan.overlap), y1 + plan.overlap)
    image = cv2.cvtColor(_input(plan, "image")[rows, :], cv2.COLOR_RGB2BGR)  # OpenCV's order
    coverage = _input(plan, "coverage")[rows, :]
    seams = _input(plan, "seams")[rows, :] > 0 if "seams" in plan.pieces else None
    found = plan.masks(image, on_surface(image, coverage, plan.level), seams)
    a, b = y0 - rows.start, y1 - rows.start
    contrast = np.clip(np.round(np.where(found.cracks[a:b], found.contrast[a:b], 0)), 0, 255)
    logits, p = None, None  # the network's, as stored (codes): what joined bands measure
    if found.probability is not None:
        logits = logit_code(found.probability[a:b])
        write_atomic(scratch / f"band{index}.logit", logits.tobytes())
        p = probability_of_code(logits)
    for name, part in (
        ("crack", found.cracks[a:b]),
        ("corrosion", found.rust[a:b]),
        ("contrast", contrast),
    ):
        write_atomic(scratch / f"band{index}.{name}", part.astype(np.uint8).tobytes())
        if name in CLASSES:
            crack = name == "crack"
            c = contrast.astype(np.float32) if crack else None  # as stored: whole levels
            cal = found.calibration if crack and p is not None else None
            data = _band_defects(part, name, c, plan.mm_per_px, y0, p if crack else None, cal)
            write_atomic(scratch / f"band{index}.{name}.parts", data)
            write_segment(scratch / f"{name}.png.d", y0, part.astype(np.uint8) * 255)


def _band_defects(
    mask: NDArray[np.bool_],
    name: str,
    contrast: NDArray[np.float32] | None,
    mm_per_px: float | None,
    y0: int,
    probability: NDArray[np.float32] | None = None,
    calibration: Calibration | None = None,
) -> bytes:
    """A band's components (8-connected; the band's first row is mosaic row ``y0``) as an
    ``.npz``: those inside the band measured (``defects``, JSON, mosaic pixels); of those
    touching its first or last row, which go on in the bands beside it, the ``boxes``
    (n, 4: x, y, w, h in band rows), ``labels`` (n) and ``seeds`` (n, 2: x, y of each one's
    first pixel in raster order); and the labels of the ``first`` and ``last`` rows."""
    comps = Components.of(mask)
    edge = np.unique(np.concatenate([comps.labels[0], comps.labels[-1]]))
    edge = edge[edge > 0]
    inner = replace(comps, keep=comps.keep.copy())
    inner.keep[edge] = False
    found = measure_defects(
        mask,
        name,
        mm_per_px=mm_per_px,
        contrast=contrast,
        components=inner,
        probability=probability,
        calibration=calibration,
    )
    boxes = comps.stats[edge, :4].astype(np.int64)
    seeds = np.array(
        [
            (x + int(np.argmax(comps.labels[y, x : x + w] == k)), y)
            for k, (x, y, w, _) in zip(edge.tolist(), boxes.tolist())
        ],
        np.int64,
    ).reshape(-1, 2)
    buf = io.BytesIO()
    np.savez(
        buf,
        defects=np.array(json.dumps([asdict(moved(d, 0, y0, d.id)) for d in found])),
        boxes=boxes,
        labels=edge,
        seeds=seeds,
        first=comps.labels[0],
        last=comps.labels[-1],
    )
    return buf.getvalue()


BUDGET_BYTES = 768 * 2**20  # a band's working set, context rows included
MIN_BAND_ROWS = 128  # twice the context rows: thinner bands would mostly repeat context
BYTES_PER_PX = 96  # measured: the detectors' intermediates per pixel of a band


MAX_PARALLEL = 4  # bands a worker searches at once, within the budget together
BANDS_TO_SHARE = 16  # bands a mosaic is cut into at most for sharing, however small
MIN_SHARED_ROWS = 256  # core rows of a band cut for sharing: its context costs at most half


def band_rows(
    width: int, overlap: int, budget_bytes: int = BUDGET_BYTES, per_px: int = BYTES_PER_PX
) -> int:
    """Core rows per band so that a band with its context rows fits the memory budget."""
    return int(max(MIN_BAND_ROWS, budget_bytes // max(1, width * per_px) - 2 * overlap))


def band_grid(width: int, height: int, overlap: int) -> int:
    """Core rows of the bands a mosaic is searched in, from its size alone: the same bands
    whoever searches it (a station's threads, any number of workers), so the same defects.
    Small enough for :data:`MAX_PARALLEL` bands in the budget at once, and cut into up to
    :data:`BANDS_TO_SHARE` bands for workers to share."""
    return min(
        band_rows(width, overlap, BUDGET_BYTES // MAX_PARALLEL),
        max(MIN_SHARED_ROWS, -(-height // BANDS_TO_SHARE)),
    )


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
    calibration: Calibration | None = None,
) -> list[Defect]:
    """Cracks and corrosion of ``results/mosaic.png`` (with its coverage and seams), band by
    band; writes the two mask PNGs into ``out`` (its scratch files too) and returns the
    measured defects (mosaic pixels).

    The PNGs' pieces, then the bands, are independent parts (``map_bands``: in turn, on
    threads, or on other workers; ``rows`` high, else :func:`band_grid`'s); the bands'
    components are then joined across seams in order, and measured (a crack's confidence
    by ``calibration`` on the network's logits, when the masks give them)."""
    header = pyvips.Image.new_from_file(str(results / "mosaic.png"))
    width, height = header.width, header.height
    rows = rows or band_grid(width, height, overlap)
    scratch = out / ".detect-scratch"
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir()
    try:
        pieces = {
            name: pieces_of(results / png, height)
            for name, (png, _) in INPUTS.items()
            if (results / png).is_file() or name != "seams"
        }
        plan = BandPlan(
            str(results), str(scratch), pieces, width, height, overlap, level, masks, mm_per_px
        )
        map_bands(unpack_piece, plan, [(n, k) for n, rs in pieces.items() for k in range(len(rs))])
        progress(0.1, "mosaic unpacked")
        cores = [(y, min(y + rows, height)) for y in range(0, height, rows)]
        map_bands(band_masks, plan, list(enumerate(cores)))
        progress(0.8, f"{len(cores)} bands searched")
        return _joined(scratch, out, cores, width, height, mm_per_px, progress, calibration)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _joined(
    scratch: Path,
    out: Path,
    cores: list[tuple[int, int]],
    width: int,
    height: int,
    mm_per_px: float | None,
    progress: Callable[[float, str], None],
    calibration: Calibration | None = None,
) -> list[Defect]:
    """The bands' components joined across their edges, in order, and measured; the mask
    PNGs joined from the bands' segments into ``out``."""
    maps = {
        n: RowFiles([scratch / f"band{k}.{n}" for k in range(len(cores))], cores, width)
        for n in ("crack", "corrosion", "contrast", "logit")
        if n != "logit" or (scratch / "band0.logit").is_file()
    }
    parts = {c: _Parts() for c in CLASSES}
    for band, (y0, _) in enumerate(cores):
        for name in CLASSES:
            _join(parts[name], scratch / f"band{band}.{name}.parts", band, y0)
    progress(0.9, "bands joined")
    for name in CLASSES:
        join_segments(scratch / f"{name}.png.d", out / f"{name}_mask.png", width, height, 1)
    found: list[Defect] = []
    for name in CLASSES:
        contrast = maps["contrast"] if name == "crack" else None
        logits = maps.get("logit") if name == "crack" and calibration is not None else None
        found += _measure(
            parts[name], maps[name], contrast, name, mm_per_px, len(found) + 1, logits, calibration
        )
    return found


class RowFiles:
    """Raw files of consecutive row ranges (``cores``: (y0, y1) each, ``width`` pixels of
    ``channels`` bytes) read as one image of the mosaic's rows, by slices, without a copy
    of the rest."""

    def __init__(
        self, files: list[Path], cores: list[tuple[int, int]], width: int, channels: int = 1
    ) -> None:
        self.files, self.cores, self.width, self.channels = files, cores, width, channels
        self.shape = (cores[-1][1] if cores else 0, width)

    def __getitem__(self, key: tuple[slice, slice]) -> NDArray[np.uint8]:
        """Rows ``ys`` and columns ``xs`` of the joined mosaic (plain slices)."""
        ys, xs = key
        y_lo, y_hi, _ = ys.indices(self.shape[0])
        pieces = []
        for path, (y0, y1) in zip(self.files, self.cores):
            a, b = max(y_lo, y0), min(y_hi, y1)
            if a < b:
                shape = (y1 - y0, self.width) + ((self.channels,) if self.channels > 1 else ())
                rows = np.memmap(path, dtype=np.uint8, mode="r", shape=shape)
                pieces.append(np.array(rows[a - y0 : b - y0, xs]))
        return np.concatenate(pieces) if pieces else np.zeros((0, 0), np.uint8)


def _join(acc: _Parts, components: Path, band: int, y0: int) -> None:
    """Record a band's components (:func:`_band_defects`, the band's first row at mosaic
    row ``y0``): its measured defects, and those on its edges linked to the band above's."""
    with np.load(components) as found:
        boxes, labels, seeds, first, last = (
            found[k] for k in ("boxes", "labels", "seeds", "first", "last")
        )
        for d in json.loads(str(found["defects"])):
            acc.inner.append(
                Defect(**{**d, "bbox": tuple(d["bbox"]), "centroid_px": tuple(d["centroid_px"])})
            )
    for lab, (x, y, w, h), (sx, sy) in zip(labels.tolist(), boxes.tolist(), seeds.tolist()):
        acc.parts[(band, lab)] = _Part(x, y0 + y, x + w, y0 + y + h, (sx, y0 + sy))
    if acc.last_row is not None:
        acc.links += [((band - 1, a), (band, b)) for a, b in seam_links(acc.last_row, first)]
    acc.last_row = last


def _measure(
    acc: _Parts,
    mask: RowFiles,
    contrast: RowFiles | None,
    name: str,
    mm_per_px: float | None,
    first_id: int,
    logits: RowFiles | None = None,
    calibration: Calibration | None = None,
) -> list[Defect]:
    """Each component on a band's edges, joined with those it touches across seams,
    measured on a crop around it; with those measured inside their bands, in reading order."""
    groups = DisjointSet(list(acc.parts))
    for a, b in acc.links:
        if a in acc.parts and b in acc.parts:
            groups.merge(a, b)
    found: list[Defect] = list(acc.inner)
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
        p = probability_of_code(logits[y0:y1, x0:x1]) if logits is not None else None
        for d in measure_defects(
            one,
            name,
            mm_per_px=mm_per_px,
            contrast=c,
            probability=p,
            calibration=calibration if p is not None else None,
        ):
            found.append(moved(d, x0, y0, first_id + len(found)))
    found.sort(key=lambda d: (d.bbox[1], d.bbox[0]))
    return [moved(d, 0, 0, first_id + i) for i, d in enumerate(found)]
