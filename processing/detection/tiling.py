"""Overlapping tiles of a large image whose cores partition it."""

from __future__ import annotations


def tile_cores(
    shape: tuple[int, int], tile_px: int, overlap_px: int
) -> list[tuple[slice, slice, slice, slice]]:
    """Tiles covering an (H, W) image: for each, the tile's (rows, cols) slices with
    ``overlap_px`` of context and, relative to the tile, the slices of its core; the
    cores partition the image."""
    if tile_px <= 2 * overlap_px:
        raise ValueError(f"tile_px ({tile_px}) must exceed twice overlap_px ({overlap_px})")
    h, w = shape
    if h <= tile_px and w <= tile_px:
        return [(slice(0, h), slice(0, w), slice(0, h), slice(0, w))]
    step = tile_px - 2 * overlap_px
    out = []
    for y in range(0, h, step):
        for x in range(0, w, step):
            y0, x0 = max(0, y - overlap_px), max(0, x - overlap_px)
            y1, x1 = min(h, y + step + overlap_px), min(w, x + step + overlap_px)
            cy1, cx1 = min(h, y + step), min(w, x + step)
            out.append(
                (slice(y0, y1), slice(x0, x1), slice(y - y0, cy1 - y0), slice(x - x0, cx1 - x0))
            )
    return out


def tile_core(rows: slice, cols: slice, core_rows: slice, core_cols: slice) -> tuple[slice, slice]:
    """A tile core's slices in image coordinates."""
    return (
        slice(rows.start + core_rows.start, rows.start + core_rows.stop),
        slice(cols.start + core_cols.start, cols.start + core_cols.stop),
    )
