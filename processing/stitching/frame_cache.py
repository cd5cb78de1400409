"""Frames for the stitcher, loaded on demand through a bounded cache: decoded, flat-field
corrected, prepared for registration once."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from threading import Event, Lock
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.stitching.mosaic import FrameSource, StitchParams
from processing.stitching.registration import Level


def gray_of(img: NDArray[np.uint8]) -> NDArray[np.uint8]:
    return cast(NDArray[np.uint8], cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)) if img.ndim == 3 else img


def estimate_flat_field(
    frames: Sequence[NDArray[np.uint8]], *, scale: int = 8
) -> NDArray[np.float32]:
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
        g = cv2.resize(gray_of(f), small, interpolation=cv2.INTER_AREA).astype(np.float32)
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
    return cast(NDArray[np.uint8], cv2.multiply(frame, f.astype(np.float32), dtype=cv2.CV_8U))


class FrameCache:
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
            raise ValueError(
                f"frame {k} is {img.shape[1]}x{img.shape[0]}; all frames must be {self.shape[1]}x{self.shape[0]}"
            )
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
                gray = gray_of(img).astype(np.float32)
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
        # flat-field correction
        return _times(img, self.inv_flat) if self.inv_flat is not None else img

    def level(self, k: int) -> Level:
        """Frame k's grey levels for registration (flat-fielded)."""
        lv = self._entry(k, True)[1]
        assert lv is not None
        return lv


def _nbytes(entry: tuple[NDArray[np.uint8], Level | None]) -> int:
    return entry[0].nbytes + (entry[1].nbytes if entry[1] is not None else 0)


def prepare_frames(source: FrameSource, params: StitchParams) -> FrameCache:
    n = len(source)
    if n == 0:
        raise ValueError("frames must not be empty")
    frames = FrameCache(source, params.cache_bytes)
    first = frames.image(0)
    frames.shape = first.shape
    if n >= params.flat_field_min_frames and not params.vignetting:  # else measured on overlaps
        picks = np.unique(
            np.linspace(0, n - 1, min(n, params.flat_field_sample)).round().astype(int)
        )
        flat = estimate_flat_field([frames.load(int(k)) for k in picks])
        if float(flat.min()) < 1.0 - params.flat_field_min_falloff:  # correct real vignetting only
            frames.inv_flat = (1.0 / np.maximum(flat, 0.2)).astype(np.float32)
    return frames
