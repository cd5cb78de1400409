"""The ``stitch`` job: the session's frames as a mosaic in world coordinates."""

from __future__ import annotations

import hashlib
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from processing.stitching import (
    MosaicLayout,
    StitchParams,
    camera_poses,
    plan_mosaic,
    render_bands,
)
from processing.stitching.alignment import PairRequest, PairSpread, measure_pair
from processing.stitching.blending import BandPainter, band_rows
from processing.stitching.frame_cache import FrameCache
from processing.stitching.registration import PairMeasurement
from server.jobs.context import JobContext, params_record
from server.storage.files import SessionFiles
from server.storage.models import Frame
from server.storage.mosaic_files import (
    BandFill,
    StoredImages,
    decodes,
    frame_records,
    image_header,
    write_band,
    write_mosaic,
)

HELPER_CACHE_BYTES = StitchParams().cache_bytes  # decoded frames a helping worker keeps
_own: dict[str, FrameCache] = {}  # frames of the stitch jobs this process runs, by preparation
_helping: list[tuple[str, FrameCache]] = []  # the one preparation this process helps with
_painter: list[tuple[str, BandPainter]] = []  # the last mosaic this process painted bands of
_scratch = threading.local()  # a thread's band accumulator
_prepared_lock = threading.Lock()


@dataclass(frozen=True)
class StoredFrames:
    """How a worker helping with the pairs loads the session's frames itself: where each is
    stored, their shape and the flat-field correction in use; ``key`` names that preparation."""

    key: str
    where: list[tuple[str, int | None, int]]
    shape: tuple[int, ...]
    inv_flat: NDArray[np.float32] | None


def _frames_of(files: SessionFiles, stored: StoredFrames) -> FrameCache:
    """The frames prepared as ``stored`` says: the job's own on its worker, else loaded
    here (one preparation kept at a time)."""
    with _prepared_lock:
        if stored.key in _own:
            return _own[stored.key]
        if _helping and _helping[0][0] == stored.key:
            return _helping[0][1]
        where = stored.where
        frames = FrameCache(
            StoredImages(lambda k: files.read(*where[k]), len(where)), HELPER_CACHE_BYTES
        )
        frames.shape, frames.inv_flat = stored.shape, stored.inv_flat
        _helping[:] = [(stored.key, frames)]
        return frames


def register_pair_part(
    files: SessionFiles, stored: StoredFrames, request: PairRequest
) -> PairMeasurement | None:
    """One pair of a stitch job, registered wherever the job queue runs it."""
    return measure_pair(_frames_of(files, stored).level, request)


def _stored(
    ctx: JobContext, where: list[tuple[str, int | None, int]], frames: FrameCache
) -> StoredFrames:
    """``frames`` as helpers load them; this worker's own parts use ``frames`` themselves."""
    flat = frames.inv_flat
    digest = hashlib.blake2b(repr(where).encode(), digest_size=8)
    if flat is not None:
        digest.update(flat.tobytes())
    # named by the job and what is prepared, not the attempt: a later attempt's plan of the
    # same pairs is the same plan, and adopts the pairs done before (server.jobs.parts)
    key = f"{ctx.job_id}-{digest.hexdigest()}"
    stored = StoredFrames(key, where, frames.shape or (), flat)
    with _prepared_lock:
        _own[stored.key] = frames
    return stored


def spread_pairs(
    ctx: JobContext, where: list[tuple[str, int | None, int]], seconds: list[float]
) -> Callable[[FrameCache], PairSpread]:
    """The stitch's pair registrations as parts of the job (:meth:`JobContext.map`); the
    job's own worker does its share with the frames it has already prepared. The seconds
    each batch of pairs took are appended to ``seconds``."""

    def spread(frames: FrameCache) -> PairSpread:
        stored = _stored(ctx, where, frames)

        def pairs(requests: Sequence[PairRequest]) -> list[PairMeasurement | None]:
            t0 = time.perf_counter()
            found = ctx.map(register_pair_part, stored, list(requests))
            seconds.append(time.perf_counter() - t0)
            return found

        return pairs

    return spread


@dataclass(frozen=True)
class BandJob:
    """What a worker rendering bands of a mosaic needs: the frames, the layout, the
    options, the raw files to write into (relative to the data directory), rows a band."""

    frames: StoredFrames
    layout: MosaicLayout
    params: StitchParams
    raw: str
    coverage: str
    rows: int


def render_band_part(files: SessionFiles, job: BandJob, y0: int) -> None:
    """One band of a stitch job's mosaic, rendered and written in place wherever the job
    queue runs it."""
    paint = _painter_for(files, job)
    acc = None
    if job.params.blend == "feather":  # each thread's accumulator, reused band after band
        acc = getattr(_scratch, job.frames.key, None)
        if acc is None:
            _scratch.__dict__.clear()
            acc = np.zeros((job.rows, job.layout.width, job.layout.channels + 1), np.float32)
            setattr(_scratch, job.frames.key, acc)
    write_band(files.resolve(job.raw), files.resolve(job.coverage), paint(y0, y0 + job.rows, acc))


def _painter_for(files: SessionFiles, job: BandJob) -> BandPainter:
    with _prepared_lock:
        if _painter and _painter[0][0] == job.frames.key:
            return _painter[0][1]
    paint = BandPainter(job.layout, _frames_of(files, job.frames), job.params)
    with _prepared_lock:
        _painter[:] = [(job.frames.key, paint)]
    return paint


def fill_over_workers(
    ctx: JobContext,
    where: list[tuple[str, int | None, int]],
    layout: MosaicLayout,
    frames: FrameCache,
    params: StitchParams,
) -> BandFill:
    """The mosaic's bands as parts of the job, each written in place by whoever renders it."""

    def fill(raw: Path, coverage: Path, height: int) -> None:
        rows = band_rows(layout, params)
        job = BandJob(
            _stored(ctx, where, frames),
            layout,
            params,
            str(raw.relative_to(ctx.files.data_dir)),
            str(coverage.relative_to(ctx.files.data_dir)),
            rows,
        )
        ctx.map(render_band_part, job, list(range(0, height, rows)))

    return fill


def _timed(fill: BandFill, seconds: list[float]) -> BandFill:
    """``fill`` that appends the seconds it took to ``seconds``."""

    def timed(raw: Path, coverage: Path, height: int) -> None:
        t0 = time.perf_counter()
        fill(raw, coverage, height)
        seconds.append(time.perf_counter() - t0)

    return timed


def _forget_prepared(ctx: JobContext) -> None:
    """Drop the frames this job prepared (here, and the preparation helped with)."""
    prefix = f"{ctx.job_id}-"
    with _prepared_lock:
        for key in [k for k in _own if k.startswith(prefix)]:
            del _own[key]
        for held in (_helping, _painter):
            if held and held[0][0].startswith(prefix):
                held.clear()
    _scratch.__dict__.clear()


def run_stitch(ctx: JobContext) -> dict[str, Any]:
    """Mosaic of the session's frames: odometry through the camera mount as the initial
    guess, every overlapping pair registered, poses solved globally, written as PNG, Deep
    Zoom pyramid, overview and world mapping with bounded memory."""
    calib = ctx.session().calibration.get("camera", {})
    px_per_m = float(calib.get("px_per_m", 0)) or None
    with ctx.factory() as db:
        frames = list(db.scalars(ctx.rows(Frame)))
    use, skipped = _readable_frames(ctx, frames)
    with_pose = all(f.pose_x is not None for f in use) and px_per_m is not None
    guess = None
    if with_pose and px_per_m is not None:
        robot = np.array([[f.pose_x, f.pose_y, f.pose_yaw] for f in use], dtype=np.float64)
        guess = camera_poses(robot, calib.get("T_robot_camera", [0.0, 0.0, 0.0]), px_per_m)
    source = StoredImages(lambda k: ctx.files.payload(use[k]), len(use))
    params = StitchParams()
    params = replace(params, registration=replace(params.registration, workers=ctx.threads))
    where = [(f.path, f.data_offset, f.size_bytes) for f in use]
    spread = ctx.fanout is not None
    banded: list[float] = []
    registered: list[float] = []
    t0 = time.perf_counter()
    try:
        layout, loaded = plan_mosaic(
            source,
            guess,
            px_per_m=px_per_m if with_pose and px_per_m else 1.0,
            params=params,
            progress=lambda f, m: ctx.progress(0.7 * f, m),
            spread=spread_pairs(ctx, where, registered) if spread else None,
        )
        t_pairs = time.perf_counter() - t0
        world = {
            "world_referenced": with_pose,
            "frames": frame_records(layout, [f.seq for f in use]),
            "skipped_frames": [f.seq for f in skipped],
        }
        if spread:
            ctx.progress(0.75, "rendering the mosaic's bands on the workers")
            bands: Any = _timed(fill_over_workers(ctx, where, layout, loaded, params), banded)
        else:
            bands = render_bands(
                layout, loaded, params, progress=lambda f, m: ctx.progress(0.7 + 0.25 * f, m)
            )
        files = write_mosaic(
            ctx.output_dir(),
            layout,
            bands,
            world=world,
            save_map=ctx.map if spread else None,
            data_dir=ctx.files.data_dir,
        )
    finally:
        _forget_prepared(ctx)
    seconds = _seconds(t_pairs, time.perf_counter() - t0 - t_pairs, registered, banded)
    return _result(ctx, files, layout, with_pose, use, skipped, seconds, params)


def _seconds(
    pairs: float, render: float, registered: list[float], banded: list[float]
) -> dict[str, float]:
    """The job's time per stage: the pairs with the pose graph (solved on the job's
    worker) and the files written here, both spread over workers on a job queue; there,
    also the registrations themselves and the bands (with the PNG's segments)."""
    seconds = {"pairs": round(pairs, 3), "render": round(render, 3)}
    if registered:
        seconds["registrations"] = round(sum(registered), 3)
    if banded:
        seconds["bands"] = round(banded[0], 3)
    return seconds


def _readable_frames(ctx: JobContext, frames: list[Frame]) -> tuple[list[Frame], list[Frame]]:
    """The frames to stitch, and those skipped: of another size than most, whose file is
    gone, or whose image data is corrupt."""
    if not frames:
        raise ValueError("the session has no camera frames")
    size = Counter((f.width, f.height) for f in frames).most_common(1)[0][0]
    use, skipped = [], []
    for f in frames:
        try:  # a frame that cannot be read is skipped, not fatal
            data = ctx.files.payload(f)
            w, h, _ = image_header(data, f"frame {f.seq}")
            ok = (w, h) == size and decodes(data)
        except (ValueError, OSError):
            ok = False
        (use if ok else skipped).append(f)
    if not use:
        raise ValueError(f"none of the session's {len(frames)} frames could be read as an image")
    return use, skipped


def _result(
    ctx: JobContext,
    files: Any,
    layout: Any,
    with_pose: bool,
    use: list[Frame],
    skipped: list[Frame],
    seconds: dict[str, float],
    params: StitchParams,
) -> dict[str, Any]:
    """The stitch job's result record: where its files are once the job is done, the
    mosaic's size and placement, what was used and skipped, the time per stage."""
    results = ctx.results_dir()
    return {
        "mosaic_path": str(results / files.mosaic.name),
        "overview_path": str(results / files.overview.name),
        "dzi_path": str(results / files.dzi.name) if files.dzi else None,
        "width_px": layout.width,
        "height_px": layout.height,
        "px_per_m": layout.px_per_m,
        "origin_m": list(layout.origin_m),
        "world_referenced": with_pose,
        "frames": len(use),
        "skipped_frames": [f.seq for f in skipped],
        "low_confidence_frames": int((~layout.confident).sum()),
        "pairs": layout.pairs,
        "rejected_pairs": layout.rejected_pairs,
        "overview_scale": files.overview_scale,
        "seconds": seconds,
        "params": params_record(params),
    }
