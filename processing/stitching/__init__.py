"""Mosaic of downward-camera frames in world coordinates (paper §3.1).

The paper's method, step by step: the camera's motion from the robot's odometry through
the frame chain image → camera → robot → world (:func:`camera_poses`) gives each frame's
initial place; appearance-based matching refines it (here sub-pixel, with rotation, over
every overlapping pair, solved globally: :mod:`processing.stitching.alignment`); exposure is
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

from collections.abc import Callable, Sequence
from dataclasses import replace

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.poses import frame_i_to_j
from processing.stitching.alignment import PairSpread, estimate_poses
from processing.stitching.blending import feather_weight, paper_blend_mask, render_bands
from processing.stitching.exposure import solve_gains
from processing.stitching.frame_cache import FrameCache, estimate_flat_field, prepare_frames
from processing.stitching.mosaic import (
    Band,
    Blend,
    FrameSource,
    Mosaic,
    MosaicLayout,
    Progress,
    StitchParams,
    camera_poses,
)
from processing.stitching.registration import PairMeasurement
from processing.stitching.vignetting import overlap_samples, solve_photometry

__all__ = [
    "Band",
    "Blend",
    "FrameSource",
    "Mosaic",
    "MosaicLayout",
    "StitchParams",
    "camera_poses",
    "estimate_flat_field",
    "feather_weight",
    "paper_blend_mask",
    "plan_mosaic",
    "render_bands",
    "stitch_frames",
]


def plan_mosaic(
    source: FrameSource,
    poses: NDArray[np.floating] | None,
    *,
    px_per_m: float = 1.0,
    params: StitchParams = StitchParams(),
    progress: Progress | None = None,
    spread: Callable[[FrameCache], PairSpread] | None = None,
) -> tuple[MosaicLayout, FrameCache]:
    """Frame poses (registered and solved globally), exposure gains and the mosaic's extent.

    ``poses`` (N, 3) are camera-centre poses in world *pixels* (see :func:`camera_poses`),
    or None to estimate the motion from the images alone (then ``px_per_m`` only labels
    the scale). ``spread(frames)`` registers pairs of the frames as prepared at that point
    (their flat-field correction) elsewhere, e.g. on other processes; default: on
    ``params.registration.workers`` threads here.
    """
    n = len(source)
    if px_per_m <= 0:
        raise ValueError(f"px_per_m must be positive, got {px_per_m}")
    known = _checked_poses(poses, n)
    frames = prepare_frames(source, params)
    shape = frames.shape
    assert shape is not None  # taken from the first frame
    measurements: list[PairMeasurement]
    if n == 1:
        est_poses = (known if known is not None else np.zeros((1, 3))).copy()
        confident, measurements, rejected = np.ones(1, bool), [], 0
    else:
        est_poses, confident, measurements, rejected = _register(
            frames, n, known, params, progress, spread
        )
    gains = _gains(n, measurements) if params.gain_compensation else np.ones(n)
    channels = 1 if len(shape) == 2 else shape[2]
    layout = MosaicLayout(
        0,
        0,
        (shape[1], shape[0]),
        channels,
        px_per_m,
        (0.0, 0.0),
        est_poses,
        confident,
        gains,
        len(measurements),
        rejected,
    )
    _fit_extent(layout, est_poses)
    return layout, frames


def _register(
    frames: FrameCache,
    n: int,
    known: NDArray[np.float64] | None,
    params: StitchParams,
    progress: Progress | None,
    spread: Callable[[FrameCache], PairSpread] | None,
) -> tuple[NDArray[np.float64], NDArray[np.bool_], list[PairMeasurement], int]:
    """The ``n`` frames' poses registered and solved globally from the ``known`` poses (or
    from the images alone), registered again once the vignetting is corrected where
    ``params`` correct it: the poses, which are confident, the pair measurements and how
    many pairs were rejected."""
    est = estimate_poses(
        frames.level,
        n,
        known,
        params.registration,
        _scaled(progress, 0.0, 0.5),
        spread(frames) if spread is not None else None,
    )
    if params.vignetting and _correct_vignetting(frames, est.measurements, params):
        # registration sees the surface evenly lit now: register again from the solution
        again = replace(params.registration, search_px=8)  # the first solution is close
        est = estimate_poses(
            frames.level,
            n,
            est.poses,
            again,
            _scaled(progress, 0.5, 1.0),
            spread(frames) if spread is not None else None,
        )
    return est.poses, est.confident, est.measurements, est.rejected


def _checked_poses(poses: NDArray[np.floating] | None, n: int) -> NDArray[np.float64] | None:
    """The camera poses as float64 (N, 3), refused unless one finite pose per frame."""
    if poses is None:
        return None
    known = np.asarray(poses, dtype=np.float64)
    if known.shape != (n, 3):
        raise ValueError(f"poses must be ({n}, 3), one per frame, got {known.shape}")
    if not np.isfinite(known).all():
        raise ValueError("poses contain NaN or infinite values")
    return known


def _fit_extent(layout: MosaicLayout, est_poses: NDArray[np.float64]) -> None:
    """Move the mosaic's origin to the frames' top-left corner and size it to hold them all."""
    boxes = np.array([layout.footprint(k) for k in range(len(est_poses))])
    x0, y0 = boxes[:, 0].min(), boxes[:, 1].min()
    layout.poses_px = est_poses - (x0, y0, 0)
    layout.width, layout.height = int(boxes[:, 2].max() - x0), int(boxes[:, 3].max() - y0)
    layout.origin_m = (float(x0) / layout.px_per_m, float(y0) / layout.px_per_m)


def _scaled(progress: Progress | None, lo: float, hi: float) -> Progress | None:
    if progress is None:
        return None
    return lambda f, m: progress(lo + (hi - lo) * f, m)


def _correct_vignetting(
    frames: FrameCache, measurements: Sequence[PairMeasurement], params: StitchParams
) -> bool:
    """Estimate the lens falloff from registered overlaps (:mod:`processing.stitching.vignetting`) on
    up to ``params.vignetting_pairs`` pairs; install its correction when it is real and
    differs from the one in use. True when frames must be registered again."""
    if not measurements:
        return False
    assert frames.shape is not None  # taken from the first frame
    h, w = frames.shape[:2]
    picks = np.unique(
        np.linspace(0, len(measurements) - 1, min(len(measurements), params.vignetting_pairs))
        .round()
        .astype(int)
    )
    # the registration's own half-resolution smoothed images, with any correction undone
    half_size = frames.level(0).half.image.shape[::-1]
    undo = (
        None
        if frames.inv_flat is None
        else cv2.resize(1.0 / frames.inv_flat, half_size, interpolation=cv2.INTER_AREA)
    )
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
    # the whole field only if so
    falls_off = float(photo.flat_field((w, h), step=8).min()) < 1.0 - params.flat_field_min_falloff
    new = (
        (1.0 / np.maximum(photo.flat_field((w, h)), 0.2)).astype(np.float32) if falls_off else None
    )
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


def stitch_frames(
    frames: FrameSource,
    poses: NDArray[np.floating] | None,
    *,
    px_per_m: float = 1.0,
    params: StitchParams = StitchParams(),
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
