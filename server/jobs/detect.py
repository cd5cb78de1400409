"""The ``detect`` job: cracks and corrosion in every frame and on the mosaic, measured,
placed on the structure, stored as defects (reviews carried over from an earlier run)."""

from __future__ import annotations

import json
import time
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from processing.detection import CrackMethod, defect_masks, find_defects
from processing.detection.confidence import Calibration
from processing.detection.corrosion import CorrosionParams
from processing.detection.crack_filter import CrackParams, SurfaceStats, measure_surface
from processing.detection.defects import Defect as Defect_
from processing.detection.defects import resolved
from processing.detection.learned import MODEL_PATH, LearnedParams, load_model
from processing.detection.surface import surface_level
from processing.poses import compose_se2, world_box
from server.jobs.banded import detect_banded
from server.jobs.context import JobContext, params_record
from server.storage.files import SessionFiles
from server.storage.models import Defect, Frame


def _defect_row(
    ctx: JobContext,
    d: Defect_,
    source: str,
    mm: bool,
    world: tuple[float, float, float, float] | None,
    frame_seq: int | None = None,
) -> Defect:
    x, y, w, h = d.bbox
    wx, wy, ww, wh = world if world is not None else (None, None, None, None)
    return Defect(
        session_id=ctx.session_id,
        job_id=ctx.job_id,
        source=source,
        frame_seq=frame_seq,
        defect_class=d.defect_class,
        bbox_x=x,
        bbox_y=y,
        bbox_w=w,
        bbox_h=h,
        area_px=d.area_px,
        length_px=d.length_px,
        max_width_px=d.max_width_px,
        mean_width_px=d.mean_width_px,
        orientation_deg=d.orientation_deg,
        length_mm=d.length_mm if mm else None,
        max_width_mm=d.max_width_mm if mm else None,
        area_mm2=d.area_mm2 if mm else None,
        world_x_m=wx,
        world_y_m=wy,
        world_w_m=ww,
        world_h_m=wh,
        confidence=d.confidence,
    )


def _detect_frames(ctx: JobContext) -> list[Defect]:
    """Defects of every camera frame, placed on the structure through the frame's pose; the
    frames are independent parts (:meth:`JobContext.map`: threads here, or other workers)."""
    calib = ctx.session().calibration.get("camera", {})
    px_per_m = float(calib.get("px_per_m", 0)) or None
    T_rc = np.array(calib.get("T_robot_camera", [0.0, 0.0, 0.0]))
    with ctx.factory() as db:
        frames = list(db.scalars(ctx.rows(Frame)))
    mm_per_px = 1000.0 / px_per_m if px_per_m else None
    ctx.progress(0.0, f"{len(frames)} frames")
    found = ctx.map(
        detect_frame,
        (mm_per_px, _method(ctx), ctx.threads),
        [(f.path, f.data_offset, f.size_bytes) for f in frames],
    )
    ctx.progress(0.5, "frames done")
    rows: list[Defect] = []
    for f, done in zip(frames, found):
        if done is not None:
            rows += _frame_rows(ctx, f, done[1], done[0], px_per_m, T_rc)
    return rows


def detect_frame(
    files: SessionFiles,
    shared: tuple[float | None, CrackMethod, int],
    where: tuple[str, int, int],
) -> tuple[tuple[int, int], list[Defect_]] | None:
    """One stored frame's (width, height) and defects (None: unreadable); ``shared`` is
    (mm per pixel, crack method, the network's threads)."""
    mm_per_px, method, threads = shared
    try:
        img = cv2.imdecode(np.frombuffer(files.read(*where), np.uint8), cv2.IMREAD_COLOR)
    except OSError:
        return None
    if img is None:
        return None
    found = find_defects(img, mm_per_px, workers=1, method=method, network_threads=threads)[2]
    return (img.shape[1], img.shape[0]), [d for d in found if resolved(d)]


def _frame_rows(
    ctx: JobContext,
    f: Frame,
    found: list[Defect_],
    size: tuple[int, int],
    px_per_m: float | None,
    T_rc: NDArray[np.float64],
) -> list[Defect]:
    """Rows of one frame's defects, placed on the structure through the frame's pose."""
    rows: list[Defect] = []
    cam = (
        compose_se2(np.array([f.pose_x, f.pose_y, f.pose_yaw]), T_rc)
        if px_per_m and f.pose_x is not None
        else None
    )
    for d in found:
        world = world_box(d.bbox, cam, px_per_m, size) if cam is not None and px_per_m else None
        rows.append(_defect_row(ctx, d, "frame", px_per_m is not None, world, frame_seq=f.seq))
    return rows


def run_detect(ctx: JobContext) -> dict[str, Any]:
    """Cracks and corrosion in every frame and on the mosaic, measured and placed on the structure."""
    t0 = time.perf_counter()
    frame_rows = _detect_frames(ctx)
    t_frames = time.perf_counter() - t0
    source = ctx.results_dir()  # the stitch job's mosaic
    if not (source / "mosaic.png").is_file() or not (source / "mosaic.json").is_file():
        raise ValueError("no mosaic to run detection on: run the stitch job first")
    world = json.loads((source / "mosaic.json").read_text())
    mm_per_px = 1000.0 / world["px_per_m"] if world.get("world_referenced") else None
    ctx.progress(0.6, "mosaic")
    surface = _frame_surface(ctx)
    out = ctx.output_dir()
    # in bands whose grid depends on the mosaic alone: the same defects whatever searches it
    found = _detect_mosaic_banded(ctx, source, out, mm_per_px, surface)
    found = [d for d in found if resolved(d)]  # a speck the camera cannot resolve is no defect
    mosaic_rows = [_mosaic_row(ctx, d, world) for d in found]
    by_class = {c: sum(1 for d in found if d.defect_class == c) for c in ("crack", "corrosion")}
    result = {
        "defects": len(found),
        "by_class": by_class,
        "frame_defects": len(frame_rows),
        "method": _method(ctx),
        "reviews_carried_over": 0,  # counted when the defects are stored
        "seconds": {  # per stage: the frames are spread over workers, the mosaic is not
            "frames": round(t_frames, 3),
            "mosaic": round(time.perf_counter() - t0 - t_frames, 3),
        },
        "crack_mask": str(ctx.results_dir() / "crack_mask.png"),
        "params": {
            "crack": _crack_record(_method(ctx)),
            "corrosion": params_record(CorrosionParams()),
        },
    }

    def store(db: Session) -> None:
        result["reviews_carried_over"] = _replace_defects(
            db, ctx.session_id, frame_rows, mosaic_rows
        )

    ctx.on_finish(store)
    return result


def _mosaic_row(ctx: JobContext, d: Defect_, world: dict[str, Any]) -> Defect:
    """A defect found on the mosaic as a row, placed on the structure when the mosaic is."""
    px_per_m, (ox, oy) = world["px_per_m"], world["origin_m"]
    referenced = bool(world.get("world_referenced"))
    x, y, w, h = d.bbox
    placed = (
        (ox + x / px_per_m, oy + y / px_per_m, w / px_per_m, h / px_per_m) if referenced else None
    )
    return _defect_row(ctx, d, "mosaic", referenced, placed)


def _replace_defects(
    db: Session, session_id: str, frame_rows: list[Defect], mosaic_rows: list[Defect]
) -> int:
    """The session's defects replaced by these, in the transaction that ends the job:
    reviews carried over to the defects found again (how many), defects drawn by hand kept,
    every defect numbered."""
    ours = (Defect.session_id == session_id) & Defect.drawn_by.is_(None)
    reviewed = list(db.scalars(select(Defect).where(ours, Defect.reviewed_by.is_not(None))))
    carried = carry_reviews(reviewed, frame_rows + mosaic_rows)
    db.execute(delete(Defect).where(ours))  # defects drawn by hand stay
    drawn = list(
        db.scalars(
            select(Defect).where(Defect.session_id == session_id, Defect.drawn_by.is_not(None))
        )
    )
    number_defects(frame_rows)
    number_defects(mosaic_rows + drawn)
    db.add_all(frame_rows + mosaic_rows)
    return carried


def _frame_surface(ctx: JobContext, n: int = 9) -> SurfaceStats | None:
    """The camera's surface statistics for ``proposed`` on the mosaic, pooled over up to
    ``n`` frames spread through the session (None without readable frames), so that every
    tile and band of the mosaic is thresholded alike."""
    with ctx.factory() as db:
        frames = list(db.scalars(ctx.rows(Frame)))
    found = []
    for i in np.unique(np.linspace(0, len(frames) - 1, n).astype(int)) if frames else []:
        try:
            data = np.frombuffer(ctx.files.payload(frames[i]), np.uint8)
        except OSError:
            continue
        image = cv2.imdecode(data, cv2.IMREAD_COLOR)
        if image is not None and min(image.shape[:2]) >= 3 and image.std() > 0:
            found.append(measure_surface(image))
    return SurfaceStats.pooled(found) if found else None


def _method(ctx: JobContext) -> CrackMethod:
    method = ctx.params.get("method", "proposed")
    if method not in ("proposed", "learned"):
        raise ValueError(f"detect method must be 'proposed' or 'learned', got {method!r}")
    return method


def _crack_record(method: CrackMethod) -> dict[str, Any]:
    """The crack detector's parameters; for the network, its training record's summary."""
    if method == "proposed":
        return params_record(CrackParams())
    record = load_model().record
    keys = ("format", "datasets", "threshold", "parameters", "train_seconds", "calibration")
    return {"method": "learned", **{k: record.get(k) for k in keys}}


def _detect_mosaic_banded(
    ctx: JobContext,
    source: Path,
    out: Path,
    mm_per_px: float | None,
    surface: SurfaceStats | None,
) -> list[Defect_]:
    """Defects of a mosaic (in ``source``) too large for memory, band by band
    (:mod:`server.jobs.banded`), the masks written into ``out``; the surface's brightness
    level comes from the overview."""
    overview = cv2.imread(str(source / "mosaic_overview.png"), cv2.IMREAD_COLOR)
    if overview is None:
        raise ValueError("mosaic_overview.png cannot be read")
    level = surface_level(overview, np.any(overview > 0, axis=2))
    masks = partial(
        defect_masks,
        crack_method=_method(ctx),
        surface=surface,
        workers=ctx.threads,
        learned_params=LearnedParams(model_path=MODEL_PATH, threads=ctx.threads),
    )
    return detect_banded(
        source,
        out,
        masks,
        mm_per_px,
        level,
        progress=lambda f, m: ctx.progress(0.6 + 0.35 * f, m),
        map_bands=ctx.map,
        # the model the bands' masks load (same path and threads): one fit for every crack
        calibration=Calibration.from_record(load_model(MODEL_PATH, ctx.threads).record)
        if _method(ctx) == "learned"
        else None,
    )


def _box_iou(a: Defect, b: Defect) -> float:
    x0, y0 = max(a.bbox_x, b.bbox_x), max(a.bbox_y, b.bbox_y)
    x1, y1 = (
        min(a.bbox_x + a.bbox_w, b.bbox_x + b.bbox_w),
        min(a.bbox_y + a.bbox_h, b.bbox_y + b.bbox_h),
    )
    inter = max(0, x1 - x0) * max(0, y1 - y0)
    union = a.bbox_w * a.bbox_h + b.bbox_w * b.bbox_h - inter
    return inter / union if union > 0 else 0.0


def along_the_structure(d: Defect) -> tuple[bool, float, float, int]:
    """The order defects are numbered and listed in: across (y), then along (x) the
    structure; unplaced ones last, in the order they were found."""
    placed = d.world_x_m is not None and d.world_y_m is not None
    return (not placed, d.world_y_m or 0.0, d.world_x_m or 0.0, d.id or 0)


def number_defects(rows: list[Defect]) -> None:
    """Give one session's defects of one source their numbers, 1.. in order along the
    structure: the number the dashboard, 3D view, reports and exports show."""
    for i, d in enumerate(sorted(rows, key=along_the_structure)):
        d.number = i + 1


def carry_reviews(reviewed: list[Defect], new: list[Defect], min_iou: float = 0.3) -> int:
    """Give each new defect the review of the reviewed old one it overlaps most (same
    class, source and frame, box IoU ≥ ``min_iou``): re-running detection keeps the
    inspectors' work. Returns how many reviews were carried over."""
    carried = 0
    for d in new:
        same = [
            r
            for r in reviewed
            if (r.defect_class, r.source, r.frame_seq) == (d.defect_class, d.source, d.frame_seq)
        ]
        best = max(same, key=lambda r: _box_iou(r, d), default=None)
        if best is not None and _box_iou(best, d) >= min_iou:
            d.review_status, d.condition_state, d.comment = (
                best.review_status,
                best.condition_state,
                best.comment,
            )
            d.reviewed_by, d.reviewed_at = best.reviewed_by, best.reviewed_at
            carried += 1
    return carried
