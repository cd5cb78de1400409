"""Mosaic files on disk: the full-resolution PNG, a Deep Zoom tile pyramid, an overview,
the coverage mask and the world mapping, written from a stream of bands.

Bands go to a raw scratch file as they are finished (bounded memory for any mosaic size),
and each band's rows are deflated into a segment of the PNG as it comes (on any worker, or
on threads beside the renderer: :mod:`server.storage.png_segments`), so the full-resolution
PNG is joined from them without compressing anything more. libvips streams the raw file
into the Deep Zoom pyramid (``mosaic.dzi`` plus ``mosaic_files/<level>/<col>_<row>.jpg``,
the layout OpenSeadragon reads), the overview and the coverage PNG.
Every output appears atomically (written under a temporary name, then renamed); the scratch
and the full-resolution PNGs are written behind (:mod:`server.storage.write_behind`).
"""

from __future__ import annotations

import json
import os
import shutil
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyvips
from numpy.typing import NDArray

from processing.stitching import Band, MosaicLayout
from server.storage.files import SessionFiles
from server.storage.png_segments import join_segments, write_segment
from server.storage.write_behind import CALL_BYTES, WriteBehind, save_behind

OVERVIEW_MAX_PX = 2048
TILE_SIZE = 254  # + 1 px overlap on each side = 256 px tiles
TILE_OVERLAP = 1


@dataclass(frozen=True)
class MosaicFiles:
    """Where a written mosaic's files are."""

    mosaic: Path
    coverage: Path
    overview: Path
    overview_scale: float
    dzi: Path | None
    world: Path


def _raw_image(path: Path, width: int, height: int, bands: int) -> pyvips.Image:
    img = pyvips.Image.rawload(str(path), width, height, bands)
    return img.copy(interpretation="srgb" if bands == 3 else "b-w")


BandFill = Callable[[Path, Path, int], None]
"""Fills the raw image and coverage files (preallocated, ``rows`` tall) with every band,
in any order (:func:`write_band`): e.g. bands rendered by several processes at once."""


def write_mosaic(
    out: Path,
    layout: MosaicLayout,
    bands: Iterable[Band] | BandFill,
    *,
    pyramid: bool = True,
    world: dict[str, Any] | None = None,
    save_map: SaveMap | None = None,
    data_dir: Path | None = None,
) -> MosaicFiles:
    """Write the mosaic of ``layout`` from its ``bands`` (top to bottom, or a fill of the
    raw files) into ``out``; with ``save_map`` the outputs (PNG, coverage, overview, Deep
    Zoom pyramid) are saved as parts of a job, ``out`` inside the shared ``data_dir``."""
    out.mkdir(parents=True, exist_ok=True)
    scratch = out / ".mosaic-scratch"
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir()
    try:
        raw, cov = scratch / "mosaic.raw", scratch / "coverage.raw"
        if callable(bands):
            for path, channels in ((raw, layout.channels), (cov, 1)):
                with path.open("wb") as fh:
                    fh.truncate(layout.width * layout.height * channels)
            bands(raw, cov, layout.height)
        else:
            _stream_bands(raw, cov, layout, bands)
        files = _save_all(out, scratch, layout, pyramid, save_map, data_dir)
        _write_world(files.world, layout, files, world or {})
        return files
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _rgb(band: Band) -> NDArray[np.uint8]:
    img = band.image
    return np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if img.ndim == 3 else img)


def _segments(raw: Path) -> Path:
    """The folder of the PNG's segments beside the raw image file."""
    return raw.parent / "png"


def _stream_bands(raw: Path, cov: Path, layout: MosaicLayout, bands: Iterable[Band]) -> None:
    rows = 0
    threads = max(1, min(2, os.cpu_count() or 1))
    pending: deque[Future[Path]] = deque()
    with (
        WriteBehind(raw) as f_img,
        WriteBehind(cov) as f_cov,
        ThreadPoolExecutor(threads, thread_name_prefix="png") as pool,
    ):
        for band in bands:
            if band.y0 != rows:
                raise ValueError(f"band at row {band.y0} arrived out of order (expected {rows})")
            img = _rgb(band)
            # deflate (which releases the GIL) beside the renderer, a band or two in flight
            pending.append(pool.submit(write_segment, _segments(raw), band.y0, img))
            f_img.write(img.data)
            f_cov.write((band.coverage.astype(np.uint8) * 255).data)
            rows += band.image.shape[0]
            while len(pending) > threads or (pending and pending[0].done()):
                pending.popleft().result()
        for future in pending:
            future.result()
    if rows != layout.height:
        raise ValueError(f"mosaic has {rows} rows, layout says {layout.height}")


def write_band(raw: Path, cov: Path, band: Band) -> None:
    """One band written in place into the preallocated raw files of a :data:`BandFill`, and
    its rows as a segment of the PNG."""
    rgb = _rgb(band)
    write_segment(_segments(raw), band.y0, rgb)
    img, covered = rgb.tobytes(), (band.coverage.astype(np.uint8) * 255).tobytes()
    width = band.coverage.shape[1]
    for path, data, channels in ((raw, img, len(img) // len(covered)), (cov, covered, 1)):
        fd, view, at = os.open(path, os.O_WRONLY), memoryview(data), band.y0 * width * channels
        try:
            while view:
                done = os.pwrite(fd, view[:CALL_BYTES], at)  # short calls: write_behind
                view, at = view[done:], at + done
        finally:
            os.close(fd)


@dataclass(frozen=True)
class RawMosaic:
    """The finished raw files of a mosaic in ``scratch`` (relative to the data directory
    when other workers save its outputs), what they hold, and the overview's scale."""

    scratch: str
    width: int
    height: int
    channels: int
    overview_scale: float


SaveMap = Callable[[Callable[[Any, RawMosaic, str], None], RawMosaic, list[str]], list[Any]]
"""Runs ``fn(files, raw, what)`` for each output (``JobContext.map``: other workers too)."""


def save_output(scratch: Path, raw: RawMosaic, what: str) -> None:
    """One output of a mosaic (``mosaic``, ``coverage``, ``overview``, ``pyramid``) saved
    from its raw files into ``scratch``; outputs are independent of each other."""
    if what == "coverage":
        coverage = _raw_image(scratch / "coverage.raw", raw.width, raw.height, 1)
        save_behind(coverage, scratch / "mosaic_coverage.png", ".png", compression=3)
        return
    if what == "mosaic":
        join_segments(scratch / "png", scratch / "mosaic.png", raw.width, raw.height, raw.channels)
        return
    image = _raw_image(scratch / "mosaic.raw", raw.width, raw.height, raw.channels)
    if what == "overview":
        scale = raw.overview_scale
        small = image.resize(scale, kernel="linear") if scale < 1.0 else image
        small.pngsave(str(scratch / "mosaic_overview.png"))
    elif what == "pyramid":
        image.dzsave(
            str(scratch / "mosaic"),
            tile_size=TILE_SIZE,
            overlap=TILE_OVERLAP,
            suffix=".jpg[Q=88]",
            depth="onepixel",
        )
    else:
        raise ValueError(f"no mosaic output {what!r}")


def save_output_part(files: SessionFiles, raw: RawMosaic, what: str) -> None:
    """:func:`save_output` as a part of a job, on whichever worker takes it."""
    save_output(files.resolve(raw.scratch), raw, what)


def _save_all(
    out: Path,
    scratch: Path,
    layout: MosaicLayout,
    pyramid: bool,
    save_map: SaveMap | None,
    data_dir: Path | None,
) -> MosaicFiles:
    scale = min(1.0, OVERVIEW_MAX_PX / max(layout.width, layout.height, 1))
    outputs = ["pyramid"] * pyramid + ["mosaic", "overview", "coverage"]  # longest first
    if save_map is not None and data_dir is not None:
        rel = str(scratch.relative_to(data_dir))
        raw = RawMosaic(rel, layout.width, layout.height, layout.channels, scale)
        save_map(save_output_part, raw, outputs)
    else:
        raw = RawMosaic(str(scratch), layout.width, layout.height, layout.channels, scale)
        for what in outputs:
            save_output(scratch, raw, what)
    for name in ("mosaic.png", "mosaic_coverage.png", "mosaic_overview.png"):
        (scratch / name).replace(out / name)
    dzi = None
    if pyramid:
        shutil.rmtree(out / "mosaic_files", ignore_errors=True)
        (scratch / "mosaic_files").replace(out / "mosaic_files")
        (scratch / "mosaic.dzi").replace(out / "mosaic.dzi")
        dzi = out / "mosaic.dzi"
    return MosaicFiles(
        out / "mosaic.png",
        out / "mosaic_coverage.png",
        out / "mosaic_overview.png",
        scale,
        dzi,
        out / "mosaic.json",
    )


def _write_world(
    path: Path, layout: MosaicLayout, files: MosaicFiles, extra: dict[str, Any]
) -> None:
    doc = {
        "width_px": layout.width,
        "height_px": layout.height,
        "px_per_m": layout.px_per_m,
        "origin_m": list(layout.origin_m),
        "overview_scale": files.overview_scale,
        "pairs": layout.pairs,
        "rejected_pairs": layout.rejected_pairs,
        "dzi": files.dzi.name if files.dzi else None,
        **extra,
    }
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc))
    tmp.replace(path)


def frame_records(layout: MosaicLayout, names: list[Any]) -> list[dict[str, Any]]:
    """One record per frame: its name or sequence number, centre (mosaic px), rotation
    (degrees), exposure gain and whether image registration placed it."""
    return [
        {
            "frame": name,
            "x": float(p[0]),
            "y": float(p[1]),
            "theta_deg": float(np.degrees(p[2])),
            "gain": float(g),
            "confident": bool(c),
        }
        for name, p, g, c in zip(names, layout.poses_px, layout.gains, layout.confident)
    ]


class ImageFiles:
    """Frames read from image files on demand (a :class:`processing.stitching.FrameSource`):
    grey and BGRA files come back as BGR."""

    def __init__(self, paths: list[Path]) -> None:
        self.paths = paths

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> np.ndarray:
        path = self.paths[index]
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{path.name}: not an image OpenCV can read")
        if img.dtype != np.uint8:
            raise ValueError(f"{path.name}: expected an 8-bit image, got {img.dtype}")
        if img.ndim == 2:
            return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR) if img.shape[2] == 4 else img


def image_header(source: Path | bytes, name: str = "") -> tuple[int, int, str]:
    """(width, height, mode) from an image's header (a file or its bytes), without decoding
    it; ValueError when it is not an image."""
    import io

    from PIL import Image, UnidentifiedImageError

    name = name or (source.name if isinstance(source, Path) else "image")
    try:
        with Image.open(io.BytesIO(source) if isinstance(source, bytes) else source) as im:
            return im.size[0], im.size[1], im.mode
    except (OSError, UnidentifiedImageError, ValueError) as exc:
        raise ValueError(f"{name}: not a readable image ({exc.__class__.__name__})") from None


def decodes(data: bytes) -> bool:
    """Whether an encoded image decodes (its header may be sound and its data not)."""
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE) is not None


class StoredImages:
    """Frames stored by the station, read and decoded on demand (a
    :class:`processing.stitching.FrameSource`); ``read(k)`` gives frame k's bytes."""

    def __init__(self, read: Callable[[int], bytes], count: int) -> None:
        self.read = read
        self.count = count

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, index: int) -> np.ndarray:
        img = cv2.imdecode(np.frombuffer(self.read(index), np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"stored frame {index} is not an image OpenCV can read")
        return img


def read_region(results: Path, x: int, y: int, w: int, h: int) -> np.ndarray:
    """BGR pixels of the full-resolution mosaic in ``[x, x+w) × [y, y+h)`` (clipped to the
    mosaic), read from the Deep Zoom tiles that cover it so the whole mosaic is never
    decoded; from ``mosaic.png`` when there is no pyramid."""
    world = json.loads((results / "mosaic.json").read_text())
    width, height = int(world["width_px"]), int(world["height_px"])
    x0, y0 = max(0, int(x)), max(0, int(y))
    x1, y1 = min(width, int(x) + int(w)), min(height, int(y) + int(h))
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"region {x},{y},{w},{h} lies outside the {width}×{height} mosaic")
    tiles = results / "mosaic_files"
    if not world.get("dzi") or not tiles.is_dir():
        img = pyvips.Image.new_from_file(str(results / "mosaic.png"), access="sequential")
        rgb = np.ndarray(
            buffer=img.crop(x0, y0, x1 - x0, y1 - y0).write_to_memory(),
            dtype=np.uint8,
            shape=(y1 - y0, x1 - x0, img.bands),
        )
        return (
            cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
            if img.bands == 3
            else cv2.cvtColor(rgb, cv2.COLOR_GRAY2BGR)
        )
    level = int(np.ceil(np.log2(max(width, height)))) if max(width, height) > 1 else 0
    out = np.zeros((y1 - y0, x1 - x0, 3), np.uint8)
    for row in range(y0 // TILE_SIZE, (y1 - 1) // TILE_SIZE + 1):
        for col in range(x0 // TILE_SIZE, (x1 - 1) // TILE_SIZE + 1):
            tile = cv2.imread(str(tiles / str(level) / f"{col}_{row}.jpg"), cv2.IMREAD_COLOR)
            if tile is None:
                raise ValueError(f"mosaic tile {level}/{col}_{row} is missing or unreadable")
            tx = col * TILE_SIZE - (TILE_OVERLAP if col > 0 else 0)  # where the tile's pixel 0 lies
            ty = row * TILE_SIZE - (TILE_OVERLAP if row > 0 else 0)
            cx0, cy0 = max(x0, col * TILE_SIZE), max(y0, row * TILE_SIZE)
            cx1, cy1 = min(x1, (col + 1) * TILE_SIZE), min(y1, (row + 1) * TILE_SIZE)
            out[cy0 - y0 : cy1 - y0, cx0 - x0 : cx1 - x0] = tile[
                cy0 - ty : cy1 - ty, cx0 - tx : cx1 - tx
            ]
    return out
