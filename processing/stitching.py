"""Mosaic of downward-camera frames in world coordinates (paper §3.1).

The paper's method, step by step: the camera's motion from the robot's odometry through
the frame chain image → camera → robot → world (:func:`camera_poses`) gives each frame's
initial place; appearance-based matching refines it (here sub-pixel, with rotation, over
every overlapping pair, solved globally: :mod:`processing.alignment`); exposure is
compensated and frames blended by the rule of eq. (2) with its threshold τ, gaps in the
new frame's region filled by a 2D median filter (:func:`paper_blend_mask`).

Beyond it: vignetting removed by a flat field, per-frame gains solved over all overlaps,
feathered blending (the default; eq. (2) and newest-on-top are options), and rendering in
horizontal bands so that a mosaic of any size is produced with bounded memory: frames are
loaded on demand through a :class:`FrameSource` and each band is handed on as soon as it
is finished (to a tiled-pyramid writer, a PNG stream, or :func:`stitch_frames`, which keeps
the whole mosaic in memory for small jobs and tests).
"""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from threading import Event, Lock, local
from typing import Literal, Protocol

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from processing.alignment import estimate_poses
from processing.exposure import solve_gains
from processing.poses import frame_i_to_j, frame_to_mosaic
from processing.registration import Level, PairMeasurement, RegistrationParams
from processing.vignetting import overlap_samples, solve_photometry

Blend = Literal["feather", "paper", "newest"]
Progress = Callable[[float, str], None]


class FrameSource(Protocol):
    """Frames by index, loaded on demand (a list of arrays is one)."""

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> NDArray[np.uint8]: ...


@dataclass(frozen=True)
class StitchParams:
    """Options of the stitcher."""

    registration: RegistrationParams = field(default_factory=RegistrationParams)
    blend: Blend = "feather"
    tau: float = 0.9  # eq. (2): the new pixel wins where τ·I2 > I1
    median_px: int = 5  # eq. (2): gaps in the new frame's region filled by a median filter
    gain_compensation: bool = True
    flat_field_min_frames: int = 8
    flat_field_sample: int = 16  # frames sampled to estimate the vignetting
    flat_field_min_falloff: float = 0.03  # corrected when the corners are this much darker
    vignetting: bool = True  # estimate the lens falloff from registered overlaps and register again
    vignetting_pairs: int = 300  # pairs sampled for it
    band_bytes: int = 96 * 2**20  # working memory of one band of the mosaic
    cache_bytes: int = 160 * 2**20  # decoded frames kept for reuse


@dataclass
class MosaicLayout:
    """Where every frame goes in the mosaic and how mosaic pixels map to the world.

    ``poses_px`` is (N, 3): frame-centre x, y in mosaic pixels and rotation in radians.
    Mosaic pixel (u, v) is at world ``origin_m + (u, v) / px_per_m``.
    """

    width: int
    height: int
    frame_size: tuple[int, int]  # (w, h)
    channels: int
    px_per_m: float
    origin_m: tuple[float, float]
    poses_px: NDArray[np.float64]
    confident: NDArray[np.bool_]
    gains: NDArray[np.float64]
    pairs: int
    rejected_pairs: int

    def to_world(self, u: float, v: float) -> tuple[float, float]:
        """World (x, y) in metres of a mosaic pixel."""
        return self.origin_m[0] + u / self.px_per_m, self.origin_m[1] + v / self.px_per_m

    def to_mosaic(self, x: float, y: float) -> tuple[float, float]:
        """Mosaic pixel (u, v) of a world point (metres)."""
        return (x - self.origin_m[0]) * self.px_per_m, (y - self.origin_m[1]) * self.px_per_m

    def footprint(self, k: int) -> tuple[int, int, int, int]:
        """Bounding box (x0, y0, x1, y1), end exclusive, of frame k in the mosaic."""
        w, h = self.frame_size
        A = frame_to_mosaic(self.poses_px[k], self.frame_size)
        pts = A[:2] @ np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
        lo, hi = np.floor(pts.min(axis=1)).astype(int), np.ceil(pts.max(axis=1)).astype(int) + 1
        return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


@dataclass
class Band:
    """Rows ``y0 .. y0 + image.shape[0]`` of the mosaic."""

    y0: int
    image: NDArray[np.uint8]
    coverage: NDArray[np.bool_]


@dataclass
class Mosaic:
    """A whole stitched mosaic in memory, with its layout."""

    image: NDArray[np.uint8]
    coverage: NDArray[np.bool_]
    layout: MosaicLayout

    @property
    def frame_poses_px(self) -> NDArray[np.float64]:
        """(N, 3): frame-centre x, y in mosaic pixels and rotation in degrees."""
        p = self.layout.poses_px
        return np.column_stack([p[:, :2], np.degrees(p[:, 2])])

    @property
    def confident(self) -> NDArray[np.bool_]:
        """Frames placed by image registration (False: odometry only)."""
        return self.layout.confident

    def to_world(self, u: float, v: float) -> tuple[float, float]:
        """World (x, y) in metres of a mosaic pixel."""
        return self.layout.to_world(u, v)


def camera_poses(robot_poses: NDArray[np.floating], T_robot_camera: Sequence[float], px_per_m: float) -> NDArray[np.float64]:
    """Camera-centre poses in world pixels from robot odometry (the paper's chain
    image → camera → robot → world: T_ic is the scale ``px_per_m``, T_cr the camera's mount
    (x, y, yaw) on the robot, T_rw the odometry (x, y, yaw))."""
    p = np.asarray(robot_poses, dtype=np.float64).reshape(-1, 3)
    mx, my, myaw = (float(v) for v in T_robot_camera)
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    x = p[:, 0] + c * mx - s * my
    y = p[:, 1] + s * mx + c * my
    return np.column_stack([x * px_per_m, y * px_per_m, p[:, 2] + myaw])


def _gray(img: NDArray[np.uint8]) -> NDArray[np.uint8]:
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img


def estimate_flat_field(frames: Sequence[NDArray[np.uint8]], *, scale: int = 8) -> NDArray[np.float32]:
    """Relative brightness of each pixel position over many frames (vignetting), (H, W).

    The per-pixel median of the frames (each divided by its own mean, at 1/``scale``
    resolution), fitted by a radial falloff c0 + c1·r² + c2·r⁴ (r normalised to 1 at the
    frame's edge midpoints), so that no trace of the surface texture stays in it (a fixed
    pattern in every frame would pull the registration towards zero motion). Dividing a
    frame by it evens out its corners.
    """
    h, w = frames[0].shape[:2]
    small = (max(w // scale, 4), max(h // scale, 4))
    stack = []
    for f in frames:
        g = cv2.resize(_gray(f), small, interpolation=cv2.INTER_AREA).astype(np.float32)
        stack.append(g / max(float(g.mean()), 1.0))
    median = np.median(np.stack(stack), axis=0).ravel()
    yy, xx = np.mgrid[0 : small[1], 0 : small[0]]
    r2 = (((xx + 0.5) / small[0] * 2 - 1) ** 2 + ((yy + 0.5) / small[1] * 2 - 1) ** 2).ravel()
    A = np.column_stack([np.ones_like(r2), r2, r2 * r2])
    (c0, c1, c2), *_ = np.linalg.lstsq(A, median, rcond=None)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    R2 = ((xs + 0.5) / w * 2 - 1) ** 2 + ((ys + 0.5) / h * 2 - 1) ** 2
    flat = c0 + c1 * R2 + c2 * R2 * R2
    return (flat / max(float(flat.mean()), 1e-6)).astype(np.float32)


def _times(frame: NDArray[np.uint8], factor: NDArray[np.float32]) -> NDArray[np.uint8]:
    """A frame multiplied pixel by pixel by a one-channel factor, rounded and saturated."""
    f = factor if frame.ndim == 2 else cv2.merge([factor] * frame.shape[2])
    return cv2.multiply(frame, f.astype(np.float32), dtype=cv2.CV_8U)


class _Frames:
    """Frames from a source, checked and cached (a bounded LRU), thread-safe; ``inv_flat``
    undoes the vignetting (applied when frames are prepared for registration or rendered)."""

    def __init__(self, source: FrameSource, capacity_bytes: int) -> None:
        self.source, self.capacity = source, capacity_bytes
        self._held = 0
        self.inv_flat: NDArray[np.float32] | None = None
        self.shape: tuple[int, ...] | None = None
        self._cache: OrderedDict[int, tuple[NDArray[np.uint8], Level | None]] = OrderedDict()
        self._lock = Lock()
        self._loading: dict[int, Event] = {}  # frames being prepared, by the thread preparing them

    def load(self, k: int) -> NDArray[np.uint8]:
        """Frame k straight from the source, checked."""
        img = self.source[k]
        if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.ndim not in (2, 3):
            raise ValueError(f"frame {k} is not an 8-bit image")
        if self.shape is not None and img.shape != self.shape:
            raise ValueError(f"frame {k} is {img.shape[1]}x{img.shape[0]}; all frames must be {self.shape[1]}x{self.shape[0]}")
        return img

    def _entry(self, k: int, level: bool) -> tuple[NDArray[np.uint8], Level | None]:
        while True:
            with self._lock:
                hit = self._cache.get(k)
                if hit is not None:
                    self._cache.move_to_end(k)
                if hit is not None and (hit[1] is not None or not level):
                    return hit
                busy = self._loading.get(k)
                if busy is None:  # this thread prepares frame k; others asking for it wait
                    busy = self._loading[k] = Event()
                    break
            busy.wait()
        try:
            img = hit[0] if hit is not None else self.load(k)
            lv = None
            if level:
                gray = _gray(img).astype(np.float32)
                lv = Level.of(gray * self.inv_flat if self.inv_flat is not None else gray)
            hit = (img, lv)
            with self._lock:
                old = self._cache.pop(k, None)
                self._held -= _nbytes(old) if old is not None else 0
                self._cache[k] = hit
                self._held += _nbytes(hit)
                while self._held > self.capacity and len(self._cache) > 1:
                    _, gone = self._cache.popitem(last=False)
                    self._held -= _nbytes(gone)
        finally:
            with self._lock:
                self._loading.pop(k).set()
        return hit

    def set_flat(self, inv_flat: NDArray[np.float32] | None) -> None:
        """Use another flat-field correction (registration levels are rebuilt)."""
        with self._lock:
            self.inv_flat = inv_flat
            self._cache = OrderedDict((k, (img, None)) for k, (img, _) in self._cache.items())
            self._held = sum(_nbytes(e) for e in self._cache.values())

    def raw(self, k: int) -> NDArray[np.uint8]:
        """Frame k as the camera took it."""
        return self._entry(k, False)[0]

    def image(self, k: int) -> NDArray[np.uint8]:
        """Frame k, flat-fielded."""
        img = self.raw(k)
        return _times(img, self.inv_flat) if self.inv_flat is not None else img  # flat-field correction

    def level(self, k: int) -> Level:
        """Frame k's grey levels for registration (flat-fielded)."""
        lv = self._entry(k, True)[1]
        assert lv is not None
        return lv


def _nbytes(entry: tuple[NDArray[np.uint8], Level | None]) -> int:
    return entry[0].nbytes + (entry[1].nbytes if entry[1] is not None else 0)


def _prepare(source: FrameSource, params: StitchParams) -> _Frames:
    n = len(source)
    if n == 0:
        raise ValueError("frames must not be empty")
    frames = _Frames(source, params.cache_bytes)
    first = frames.image(0)
    frames.shape = first.shape
    if n >= params.flat_field_min_frames and not params.vignetting:  # else measured on overlaps
        picks = np.unique(np.linspace(0, n - 1, min(n, params.flat_field_sample)).round().astype(int))
        flat = estimate_flat_field([frames.load(int(k)) for k in picks])
        if float(flat.min()) < 1.0 - params.flat_field_min_falloff:  # correct real vignetting only
            frames.inv_flat = (1.0 / np.maximum(flat, 0.2)).astype(np.float32)
    return frames


def plan_mosaic(
    source: FrameSource, poses: NDArray[np.floating] | None, *, px_per_m: float = 1.0, params: StitchParams = StitchParams(),
    progress: Progress | None = None,
) -> tuple[MosaicLayout, _Frames]:
    """Frame poses (registered and solved globally), exposure gains and the mosaic's extent.

    ``poses`` (N, 3) are camera-centre poses in world *pixels* (see :func:`camera_poses`),
    or None to estimate the motion from the images alone (then ``px_per_m`` only labels
    the scale).
    """
    n = len(source)
    if px_per_m <= 0:
        raise ValueError(f"px_per_m must be positive, got {px_per_m}")
    if poses is not None:
        poses = np.asarray(poses, dtype=np.float64)
        if poses.shape != (n, 3):
            raise ValueError(f"poses must be ({n}, 3), one per frame, got {poses.shape}")
        if not np.isfinite(poses).all():
            raise ValueError("poses contain NaN or infinite values")
    frames = _prepare(source, params)
    h, w = frames.shape[:2]  # type: ignore[index]
    if n == 1:
        est_poses = (poses if poses is not None else np.zeros((1, 3))).copy()
        confident, measurements, rejected = np.ones(1, bool), [], 0
    else:
        est = estimate_poses(frames.level, n, poses, params.registration, _scaled(progress, 0.0, 0.5))
        if params.vignetting and _correct_vignetting(frames, est.measurements, params):
            # registration sees the surface evenly lit now: register again from the solution
            again = replace(params.registration, search_px=8)  # the first solution is close
            est = estimate_poses(frames.level, n, est.poses, again, _scaled(progress, 0.5, 1.0))
        est_poses, confident, measurements, rejected = est.poses, est.confident, est.measurements, est.rejected
    gains = _gains(n, measurements) if params.gain_compensation else np.ones(n)
    layout = MosaicLayout(0, 0, (w, h), 1 if len(frames.shape) == 2 else frames.shape[2], px_per_m, (0.0, 0.0),  # type: ignore[arg-type]
                          est_poses, confident, gains, len(measurements), rejected)
    boxes = np.array([layout.footprint(k) for k in range(n)])
    x0, y0 = boxes[:, 0].min(), boxes[:, 1].min()
    layout.poses_px = est_poses - (x0, y0, 0)
    layout.width, layout.height = int(boxes[:, 2].max() - x0), int(boxes[:, 3].max() - y0)
    layout.origin_m = (float(x0) / px_per_m, float(y0) / px_per_m)
    return layout, frames


def _scaled(progress: Progress | None, lo: float, hi: float) -> Progress | None:
    if progress is None:
        return None
    return lambda f, m: progress(lo + (hi - lo) * f, m)


def _correct_vignetting(frames: _Frames, measurements: Sequence[PairMeasurement], params: StitchParams) -> bool:
    """Estimate the lens falloff from registered overlaps (:mod:`processing.vignetting`) on
    up to ``params.vignetting_pairs`` pairs; install its correction when it is real and
    differs from the one in use. True when frames must be registered again."""
    if not measurements:
        return False
    h, w = frames.shape[:2]  # type: ignore[index]
    picks = np.unique(np.linspace(0, len(measurements) - 1, min(len(measurements), params.vignetting_pairs)).round().astype(int))
    # the registration's own half-resolution smoothed images, with any correction undone
    half_size = frames.level(0).half.image.shape[::-1]
    undo = None if frames.inv_flat is None else cv2.resize(1.0 / frames.inv_flat, half_size, interpolation=cv2.INTER_AREA)
    to_half = np.diag([0.5, 0.5, 1.0])

    def grey(k: int) -> NDArray[np.float32]:
        img = frames.level(k).half.image
        return img if undo is None else img * undo

    samples = []
    for idx in picks:
        m = measurements[int(idx)]
        M = to_half @ frame_i_to_j(m.delta, (w, h)) @ np.linalg.inv(to_half)
        ri, rj, lr = overlap_samples(grey(m.i), grey(m.j), M)
        if len(lr):
            samples.append((m.i, m.j, ri, rj, lr))
    photo = solve_photometry(len(frames.source), samples)
    if photo is None:
        return False
    falls_off = float(photo.flat_field((w, h), step=8).min()) < 1.0 - params.flat_field_min_falloff  # the whole field only if so
    new = (1.0 / np.maximum(photo.flat_field((w, h)), 0.2)).astype(np.float32) if falls_off else None
    old = frames.inv_flat
    if new is None and old is None:
        return False
    if new is not None and old is not None and float(np.abs(new - old).max()) < 0.005:
        return False
    frames.set_flat(new)
    return True


def _gains(n: int, measurements: Sequence[PairMeasurement]) -> NDArray[np.float64]:
    g = solve_gains(n, measurements)
    return np.clip(g / np.median(g), 0.5, 2.0)


def feather_weight(size: tuple[int, int]) -> NDArray[np.float32]:
    """Blending weight of a frame's pixels: highest at the centre, falling to ~0 at the edge
    (the product of the distances to the borders, normalised)."""
    w, h = size
    wx = np.minimum(np.arange(w) + 1.0, w - np.arange(w)) / (w / 2)
    wy = np.minimum(np.arange(h) + 1.0, h - np.arange(h)) / (h / 2)
    return np.outer(wy, wx).astype(np.float32)


def paper_blend_mask(existing: NDArray[np.uint8], new: NDArray[np.uint8], covered: NDArray[np.bool_], tau: float, median_px: int) -> NDArray[np.bool_]:
    """Where the new frame's pixel replaces the mosaic's: eq. (2), I = I2 if τ·I2 > I1 else
    I1, on grey levels, the region's gaps filled by a 2D median filter; everywhere the
    mosaic has nothing yet."""
    take = tau * _gray(new).astype(np.float32) > _gray(existing).astype(np.float32)
    if median_px > 1:
        take = cv2.medianBlur(take.astype(np.uint8) * 255, median_px | 1) > 0
    return take | ~covered


def band_rows(layout: MosaicLayout, params: StitchParams, in_flight: int = 1) -> int:
    """Height of a rendering band: at most as many rows as the working-memory budget allows
    with ``in_flight`` bands rendered at once (accumulators and finished bands), and the
    bands a multiple of ``in_flight`` in number, so that no worker idles while another
    renders the last band (3 bands on 2 threads took as long as 4)."""
    c = layout.channels
    per_row = max(layout.width, 1) * ((c + 1) * 4 * (params.blend == "feather") + c + 1) * (in_flight + 1)
    rows = int(np.clip(params.band_bytes // per_row, 32, 2048))
    bands = -(-max(layout.height, 1) // rows)
    bands = -(-bands // in_flight) * in_flight
    return max(32, -(-max(layout.height, 1) // bands))


def render_bands(layout: MosaicLayout, frames: _Frames, params: StitchParams = StitchParams(), progress: Progress | None = None) -> Iterator[Band]:
    """The mosaic, top to bottom, one band at a time (bounded memory for any size); bands
    are rendered on ``params.registration.workers`` threads, at most that many at once."""
    n = len(layout.poses_px)
    boxes = np.array([layout.footprint(k) for k in range(n)])
    workers = max(1, params.registration.workers)
    rows = band_rows(layout, params, workers)
    # feather weights in 1/255 steps: at least 1 inside the frame, 0 on its outermost pixels
    # (so no pixel blends in the black outside a frame); frames are warped as 8-bit with
    # the weight as their last channel
    weight = np.maximum(np.round(255 * feather_weight(layout.frame_size)), 1).astype(np.uint8)
    weight[[0, -1], :] = weight[:, [0, -1]] = 0
    flat_c = None
    if frames.inv_flat is not None:
        flat_c = cv2.merge([frames.inv_flat] * layout.channels) if layout.channels > 1 else frames.inv_flat
    starts = list(range(0, layout.height, rows))

    scratch = local()  # each worker thread's accumulator, reused band after band (no fresh pages)

    def render(y0: int) -> Band:
        y1 = min(layout.height, y0 + rows)
        hits = np.nonzero((boxes[:, 1] < y1) & (boxes[:, 3] > y0))[0]
        if params.blend == "feather" and getattr(scratch, "acc", None) is None:
            scratch.acc = np.zeros((rows, layout.width, layout.channels + 1), np.float32)  # zeroed again as read
        acc = scratch.acc[: y1 - y0] if params.blend == "feather" else None
        return _render_band(layout, frames, params, y0, y1, hits, weight, flat_c, acc)

    with ThreadPoolExecutor(workers) as pool:
        pending: deque[Future[Band]] = deque()
        for y0 in starts:
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


def _band_source(layout: MosaicLayout, k: int, x0: int, y0: int, w: int, h: int) -> tuple[NDArray[np.float64], tuple[slice, slice]]:
    """The part of frame k that lands in the mosaic rectangle (x0, y0, w, h), and the 2x3
    map from that part's pixels to the rectangle's."""
    A = frame_to_mosaic(layout.poses_px[k], layout.frame_size)
    A[:2, 2] -= (x0, y0)
    corners = np.linalg.inv(A) @ np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float).T
    fw, fh = layout.frame_size
    sx0, sy0 = (max(0, int(np.floor(v)) - 1) for v in corners[:2].min(axis=1))
    sx1, sy1 = min(fw, int(np.ceil(corners[0].max())) + 2), min(fh, int(np.ceil(corners[1].max())) + 2)
    A = A @ np.array([[1, 0, sx0], [0, 1, sy0], [0, 0, 1.0]])
    return A[:2], (slice(sy0, max(sy1, sy0 + 1)), slice(sx0, max(sx1, sx0 + 1)))


def _band_pieces(layout: MosaicLayout, y0: int, y1: int, hits: NDArray[np.int64]
                 ) -> Iterator[tuple[int, float, NDArray[np.float64], tuple[slice, slice], tuple[slice, slice], tuple[int, int]]]:
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


def _render_band(layout: MosaicLayout, frames: _Frames, params: StitchParams, y0: int, y1: int, hits: NDArray[np.int64],
                 weight: NDArray[np.uint8], flat_c: NDArray[np.float32] | None, acc: NDArray[np.float32] | None = None) -> Band:
    W, H, C = layout.width, y1 - y0, layout.channels
    if params.blend == "feather":
        return _feather_band(layout, frames, y0, y1, hits, weight, flat_c, acc)
    covered = np.zeros((H, W), bool)
    out = np.zeros((H, W) if C == 1 else (H, W, C), np.uint8)
    for k, gain, A, src, region, size in _band_pieces(layout, y0, y1, hits):
        img = frames.image(k)[src]
        src8 = img if gain == 1.0 else cv2.convertScaleAbs(img, alpha=gain)
        warped = cv2.warpAffine(src8, A, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        inside = cv2.warpAffine(np.full(src8.shape[:2], 255, np.uint8), A, size, flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        inside = cv2.erode(inside, np.ones((3, 3), np.uint8)) > 0
        if params.blend == "paper":
            take = paper_blend_mask(out[region], warped, covered[region], params.tau, params.median_px) & inside
        else:
            take = inside
        out[region][take] = warped[take]
        covered[region] |= inside
    return Band(y0, out, covered)


def _feather_band(layout: MosaicLayout, frames: _Frames, y0: int, y1: int, hits: NDArray[np.int64], weight: NDArray[np.uint8],
                  flat_c: NDArray[np.float32] | None, acc: NDArray[np.float32] | None = None) -> Band:
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
            img = cv2.multiply(img, flat_c[src], scale=gain, dtype=cv2.CV_8U)
        elif gain != 1.0:
            img = cv2.convertScaleAbs(img, alpha=gain)
        with_w = cv2.cvtColor(img, cv2.COLOR_BGR2BGRA if C == 3 else cv2.COLOR_GRAY2BGRA)
        with_w = with_w if C == 3 else np.ascontiguousarray(with_w[..., :2])
        with_w[..., C] = weight[src]
        warped = cv2.warpAffine(with_w, A, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        _accumulate(warped, acc[region])  # a view of the band, row stride and all
    out = np.empty((H, W, C), np.uint8)
    covered = np.empty((H, W), bool)
    _normalise(acc, out, covered)
    return Band(y0, out[..., 0] if C == 1 else out, covered)


@numba.njit(nogil=True, cache=True, fastmath=True)
def _accumulate(warped: NDArray[np.uint8], acc: NDArray[np.float32]) -> None:  # pragma: no cover - compiled
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
def _normalise(acc: NDArray[np.float32], out: NDArray[np.uint8], covered: NDArray[np.bool_]) -> None:  # pragma: no cover - compiled
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
                out[y, x, c] = np.uint8(min(acc[y, x, c] * scale + np.float32(0.5), np.float32(255.0)))
        acc[y] = 0.0


def stitch_frames(
    frames: FrameSource, poses: NDArray[np.floating] | None, *, px_per_m: float = 1.0, params: StitchParams = StitchParams(),
    progress: Progress | None = None,
) -> Mosaic:
    """Stitch frames into one in-memory mosaic in world orientation.

    Parameters
    ----------
    frames : (H, W) or (H, W, 3) uint8 frames, all the same size (a list, or any
        :class:`FrameSource`).
    poses : (N, 3) camera-centre x, y in world metres and yaw in radians (the odometry
        guess); None to estimate the motion from the images alone.
    px_per_m : image scale (pixels per metre on the surface).
    """
    guess = None
    if poses is not None:
        p = np.asarray(poses, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"poses must be ({len(frames)}, 3), one per frame, got {p.shape}")
        guess = np.column_stack([p[:, :2] * px_per_m, p[:, 2]])
    layout, loaded = plan_mosaic(frames, guess, px_per_m=px_per_m, params=params, progress=progress)
    shape = (layout.height, layout.width) + ((layout.channels,) if layout.channels > 1 else ())
    image = np.zeros(shape, np.uint8)
    coverage = np.zeros((layout.height, layout.width), bool)
    for band in render_bands(layout, loaded, params):
        image[band.y0 : band.y0 + band.image.shape[0]] = band.image
        coverage[band.y0 : band.y0 + band.image.shape[0]] = band.coverage
    return Mosaic(image, coverage, layout)
