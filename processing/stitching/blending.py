"""Rendering the mosaic band by band: frames warped to their place and blended (feathered,
eq. (2) of the paper, or newest on top), with bounded memory for a mosaic of any size."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from threading import local
from typing import cast

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from processing.poses import frame_to_mosaic
from processing.stitching.frame_cache import FrameCache, gray_of
from processing.stitching.mosaic import Band, MosaicLayout, Progress, StitchParams


def feather_weight(size: tuple[int, int]) -> NDArray[np.float32]:
    """Blending weight of a frame's pixels: highest at the centre, falling to ~0 at the edge
    (the product of the distances to the borders, normalised)."""
    w, h = size
    wx = np.minimum(np.arange(w) + 1.0, w - np.arange(w)) / (w / 2)
    wy = np.minimum(np.arange(h) + 1.0, h - np.arange(h)) / (h / 2)
    return np.outer(wy, wx).astype(np.float32)


def paper_blend_mask(
    existing: NDArray[np.uint8],
    new: NDArray[np.uint8],
    covered: NDArray[np.bool_],
    tau: float,
    median_px: int,
) -> NDArray[np.bool_]:
    """Where the new frame's pixel replaces the mosaic's: eq. (2), I = I2 if τ·I2 > I1 else
    I1, on grey levels, the region's gaps filled by a 2D median filter; everywhere the
    mosaic has nothing yet."""
    take = tau * gray_of(new).astype(np.float32) > gray_of(existing).astype(np.float32)
    if median_px > 1:
        take = cv2.medianBlur(take.astype(np.uint8) * 255, median_px | 1) > 0
    return take | ~covered


BANDS_IN_FLIGHT = 4  # bands a mosaic's grid is sized for rendering at once


def band_rows(layout: MosaicLayout, params: StitchParams) -> int:
    """Height of a rendering band, from the mosaic and the parameters alone: the same grid
    whatever renders it (threads or workers, any number of either), because a band's warps
    round at its own origin and a different grid moves a few pixels by a grey level. At
    most as many rows as the working-memory budget allows with :data:`BANDS_IN_FLIGHT`
    bands rendered at once (accumulators and finished bands), and the bands a multiple of
    it in number, so that no worker idles while another renders the last band (3 bands
    on 2 threads took as long as 4)."""
    c, in_flight = layout.channels, BANDS_IN_FLIGHT
    per_row = (
        max(layout.width, 1) * ((c + 1) * 4 * (params.blend == "feather") + c + 1) * (in_flight + 1)
    )
    rows = int(np.clip(params.band_bytes // per_row, 32, 2048))
    bands = -(-max(layout.height, 1) // rows)
    bands = -(-bands // in_flight) * in_flight
    return max(32, -(-max(layout.height, 1) // bands))


class BandPainter:
    """Renders any band of the mosaic of ``layout`` from ``frames``, in any order and from
    any thread (or process: each holding its own painter)."""

    def __init__(
        self, layout: MosaicLayout, frames: FrameCache, params: StitchParams = StitchParams()
    ) -> None:
        self.layout, self.frames, self.params = layout, frames, params
        n = len(layout.poses_px)
        self.boxes = np.array([layout.footprint(k) for k in range(n)]).reshape(-1, 4)
        # feather weights in 1/255 steps: at least 1 inside the frame, 0 on its outermost
        # pixels (so no pixel blends in the black outside a frame); frames are warped as
        # 8-bit with the weight as their last channel
        weight = np.maximum(np.round(255 * feather_weight(layout.frame_size)), 1).astype(np.uint8)
        weight[[0, -1], :] = weight[:, [0, -1]] = 0
        self.weight = weight
        self.flat_c: NDArray[np.float32] | None = None
        if frames.inv_flat is not None:
            self.flat_c = (
                cast(NDArray[np.float32], cv2.merge([frames.inv_flat] * layout.channels))
                if layout.channels > 1
                else frames.inv_flat
            )

    def __call__(self, y0: int, y1: int, acc: NDArray[np.float32] | None = None) -> Band:
        """Rows ``y0 .. y1`` (``acc``: a zeroed (≥ y1 - y0, W, C + 1) float32 accumulator
        to reuse; left zeroed again)."""
        y1 = min(self.layout.height, y1)
        hits = np.nonzero((self.boxes[:, 1] < y1) & (self.boxes[:, 3] > y0))[0]
        if acc is not None:
            acc = acc[: y1 - y0]
        return _render_band(
            self.layout, self.frames, self.params, y0, y1, hits, self.weight, self.flat_c, acc
        )


def render_bands(
    layout: MosaicLayout,
    frames: FrameCache,
    params: StitchParams = StitchParams(),
    progress: Progress | None = None,
) -> Iterator[Band]:
    """The mosaic, top to bottom, one band at a time (bounded memory for any size); bands
    are rendered on ``params.registration.workers`` threads, at most that many at once."""
    workers = max(1, params.registration.workers)
    rows = band_rows(layout, params)
    paint = BandPainter(layout, frames, params)
    scratch = local()  # each worker thread's accumulator, reused band after band (no fresh pages)

    def render(y0: int) -> Band:
        if params.blend == "feather" and getattr(scratch, "acc", None) is None:
            # zeroed again as read
            scratch.acc = np.zeros((rows, layout.width, layout.channels + 1), np.float32)
        return paint(y0, y0 + rows, scratch.acc if params.blend == "feather" else None)

    with ThreadPoolExecutor(workers) as pool:
        pending: deque[Future[Band]] = deque()
        for y0 in range(0, layout.height, rows):
            pending.append(pool.submit(render, y0))
            if len(pending) >= workers:
                yield _done(pending.popleft(), layout, progress)
        while pending:
            yield _done(pending.popleft(), layout, progress)


def _done(future: Future[Band], layout: MosaicLayout, progress: Progress | None) -> Band:
    band = future.result()
    if progress is not None:
        y1 = band.y0 + band.image.shape[0]
        progress(y1 / max(layout.height, 1), f"rendered {y1}/{layout.height} rows")
    return band


def _band_source(
    layout: MosaicLayout, k: int, x0: int, y0: int, w: int, h: int
) -> tuple[NDArray[np.float64], tuple[slice, slice]]:
    """The part of frame k that lands in the mosaic rectangle (x0, y0, w, h), and the 2x3
    map from that part's pixels to the rectangle's."""
    A = frame_to_mosaic(layout.poses_px[k], layout.frame_size)
    A[:2, 2] -= (x0, y0)
    corners = np.linalg.inv(A) @ np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float).T
    fw, fh = layout.frame_size
    sx0, sy0 = (max(0, int(np.floor(v)) - 1) for v in corners[:2].min(axis=1))
    sx1, sy1 = (
        min(fw, int(np.ceil(corners[0].max())) + 2),
        min(fh, int(np.ceil(corners[1].max())) + 2),
    )
    A = A @ np.array([[1, 0, sx0], [0, 1, sy0], [0, 0, 1.0]])
    return A[:2], (slice(sy0, max(sy1, sy0 + 1)), slice(sx0, max(sx1, sx0 + 1)))


def _band_pieces(
    layout: MosaicLayout, y0: int, y1: int, hits: NDArray[np.int64]
) -> Iterator[
    tuple[
        int, float, NDArray[np.float64], tuple[slice, slice], tuple[slice, slice], tuple[int, int]
    ]
]:
    """For each frame in ``hits`` that reaches rows y0..y1: its index, gain, the map from
    its source part to the band region, that source part (slices of the frame), the region
    (slices of the band) and the region's (w, h)."""
    W = layout.width
    for k in hits:
        bx0, by0, bx1, by1 = layout.footprint(int(k))
        cx0, cy0, cx1, cy1 = max(bx0, 0), max(by0, y0), min(bx1, W), min(by1, y1)
        if cx1 <= cx0 or cy1 <= cy0:
            continue
        A, src = _band_source(layout, int(k), cx0, cy0, cx1 - cx0, cy1 - cy0)
        region = (slice(cy0 - y0, cy1 - y0), slice(cx0, cx1))
        yield int(k), float(layout.gains[k]), A, src, region, (cx1 - cx0, cy1 - cy0)


def _render_band(
    layout: MosaicLayout,
    frames: FrameCache,
    params: StitchParams,
    y0: int,
    y1: int,
    hits: NDArray[np.int64],
    weight: NDArray[np.uint8],
    flat_c: NDArray[np.float32] | None,
    acc: NDArray[np.float32] | None = None,
) -> Band:
    W, H, C = layout.width, y1 - y0, layout.channels
    if params.blend == "feather":
        return _feather_band(layout, frames, y0, y1, hits, weight, flat_c, acc)
    covered = np.zeros((H, W), bool)
    out = np.zeros((H, W) if C == 1 else (H, W, C), np.uint8)
    for k, gain, A, src, region, size in _band_pieces(layout, y0, y1, hits):
        img = frames.image(k)[src]
        src8 = img if gain == 1.0 else cv2.convertScaleAbs(img, alpha=gain)
        warped = cast(
            NDArray[np.uint8],
            cv2.warpAffine(src8, A, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT),
        )
        footprint = cv2.warpAffine(
            np.full(src8.shape[:2], 255, np.uint8),
            A,
            size,
            flags=cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT,
        )
        inside = cv2.erode(footprint, np.ones((3, 3), np.uint8)) > 0
        if params.blend == "paper":
            take = (
                paper_blend_mask(out[region], warped, covered[region], params.tau, params.median_px)
                & inside
            )
        else:
            take = inside
        out[region][take] = warped[take]
        covered[region] |= inside
    return Band(y0, out, covered)


def _feather_band(
    layout: MosaicLayout,
    frames: FrameCache,
    y0: int,
    y1: int,
    hits: NDArray[np.int64],
    weight: NDArray[np.uint8],
    flat_c: NDArray[np.float32] | None,
    acc: NDArray[np.float32] | None = None,
) -> Band:
    """Rows y0..y1 of the feathered mosaic. Each frame, corrected (gain, flat field) and
    rounded to 8 bits, is warped with its weight as a fourth channel (four-channel 8-bit
    warps are OpenCV's fast path: three channels are ~4x slower, float ones need 4x the
    memory traffic) and added into ``acc`` (zeros; left zeroed for the next band)."""
    W, H, C = layout.width, y1 - y0, layout.channels
    if acc is None or acc.shape != (H, W, C + 1):
        acc = np.zeros((H, W, C + 1), np.float32)
    for k, gain, A, src, region, size in _band_pieces(layout, y0, y1, hits):
        img = frames.raw(k)[src]
        if flat_c is not None:  # exposure gain and flat field, rounded and saturated to 8 bits
            img = cast(
                NDArray[np.uint8], cv2.multiply(img, flat_c[src], scale=gain, dtype=cv2.CV_8U)
            )
        elif gain != 1.0:
            img = cast(NDArray[np.uint8], cv2.convertScaleAbs(img, alpha=gain))
        with_w = cv2.cvtColor(img, cv2.COLOR_BGR2BGRA if C == 3 else cv2.COLOR_GRAY2BGRA)
        with_w = with_w if C == 3 else np.ascontiguousarray(with_w[..., :2])
        with_w[..., C] = weight[src]
        warped = cast(
            NDArray[np.uint8],
            cv2.warpAffine(with_w, A, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT),
        )
        _accumulate(warped, acc[region])  # a view of the band, row stride and all
    out = np.empty((H, W, C), np.uint8)
    covered = np.empty((H, W), bool)
    _normalise(acc, out, covered)
    return Band(y0, out[..., 0] if C == 1 else out, covered)


@numba.njit(nogil=True, cache=True, fastmath=True)
def _accumulate(
    warped: NDArray[np.uint8], acc: NDArray[np.float32]
) -> None:  # pragma: no cover - compiled
    """Add a warped frame into the accumulator: Σ w·I per channel and 255·Σ w, with w the
    warped frame's last channel (its interpolated feather weight). Colour and grey frames
    have their own loop (unrolled channels: 2x faster than a loop over them)."""
    rows, cols, channels = warped.shape
    if channels == 4:
        for y in range(rows):
            for x in range(cols):
                w = np.float32(warped[y, x, 3])
                acc[y, x, 0] += np.float32(warped[y, x, 0]) * w
                acc[y, x, 1] += np.float32(warped[y, x, 1]) * w
                acc[y, x, 2] += np.float32(warped[y, x, 2]) * w
                acc[y, x, 3] += w * np.float32(255.0)
    else:
        for y in range(rows):
            for x in range(cols):
                w = np.float32(warped[y, x, 1])
                acc[y, x, 0] += np.float32(warped[y, x, 0]) * w
                acc[y, x, 1] += w * np.float32(255.0)


@numba.njit(nogil=True, cache=True, fastmath=True)
def _normalise(
    acc: NDArray[np.float32], out: NDArray[np.uint8], covered: NDArray[np.bool_]
) -> None:  # pragma: no cover - compiled
    """Feathered colour Σ w·I / Σ w, rounded and saturated to 8 bits, from an accumulator
    whose last channel is 255·Σ w; pixels no frame reached stay black and uncovered. The
    accumulator is left zeroed."""
    rows, cols, channels = out.shape
    for y in range(rows):
        for x in range(cols):
            total = acc[y, x, channels]
            covered[y, x] = total > 0
            scale = np.float32(255.0) / max(total, np.float32(1e-30))  # 0 where nothing landed
            for c in range(channels):  # float32 throughout: 3x faster than int() rounding
                out[y, x, c] = np.uint8(
                    min(acc[y, x, c] * scale + np.float32(0.5), np.float32(255.0))
                )
        acc[y] = 0.0
