"""Job bodies, run in worker processes: load rows and files, call ``processing``, store results.

This is the edge where files and rows become arrays and back; the algorithms themselves
live in ``processing``.
"""

from __future__ import annotations

import json
import logging
import traceback
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from sqlalchemy import delete, select
from sqlalchemy.orm import Session, sessionmaker

from processing.defects import Defect as Defect_
from processing.defects import measure_defects
from processing.detection import (
    CorrosionParams,
    CrackParams,
    defect_masks,
    on_surface,
    surface_level,
)
from processing.mapping import MapParams, register_clouds
from processing.poses import (
    compose_se2,
    format_tum,
    image_to_world,
    se2_matrix,
    se2_to_se3,
    transfer_correction,
)
from processing.stitching import StitchParams, camera_poses, plan_mosaic, render_bands
from robot_link.clouds import decode_cloud
from server.storage.models import Cloud, Defect, Frame, InspectionSession, Job, JobState, utcnow
from server.storage.mosaic_files import StoredImages, frame_records, image_header, write_mosaic
from server.storage.files import SessionFiles, write_atomic

log = logging.getLogger(__name__)

MOSAIC_IN_MEMORY_PX = 48_000_000  # larger mosaics are searched band by band with bounded memory
# (kind, needs: fails without them, uses: waits for them and uses their results if any)
PIPELINE: list[tuple[str, list[str], list[str]]] = [("stitch", [], []), ("map", [], ["stitch"]), ("detect", ["stitch"], []),
                                                    ("export", [], ["stitch", "map", "detect"])]


@dataclass
class JobContext:
    """What a job body gets: its row's ids, the database and the data directory."""

    job_id: int
    session_id: str
    factory: sessionmaker[Session]
    files: SessionFiles

    def progress(self, fraction: float, message: str = "") -> None:
        """Record progress (0-1) and a short message."""
        with self.factory() as db:
            job = db.get(Job, self.job_id)
            if job is not None:
                job.progress = float(min(max(fraction, 0.0), 1.0))
                job.message = message
                db.commit()

    def session(self) -> InspectionSession:
        """The job's session row."""
        with self.factory() as db:
            s = db.get(InspectionSession, self.session_id)
            if s is None:
                raise ValueError(f"session {self.session_id} no longer exists")
            return s

    def results_dir(self) -> Path:
        """Folder for this session's result files."""
        d = self.files.results_dir(self.session_id)
        d.mkdir(parents=True, exist_ok=True)
        return d


@lru_cache(maxsize=4)
def _factory(database_url: str) -> sessionmaker[Session]:
    from server.storage.db import make_engine, make_sessionmaker

    return make_sessionmaker(make_engine(database_url))


def run_job(job_id: int, database_url: str, data_dir: str) -> None:
    """Run one job to completion, recording success or the reason it failed."""
    factory = _factory(database_url)
    with factory() as db:
        job = db.get(Job, job_id)
        if job is None:
            return
        job.state, job.started_at, job.progress, job.error = JobState.running, utcnow(), 0.0, None
        db.commit()
        kind, session_id = job.kind, job.session_id
    ctx = JobContext(job_id, session_id, factory, SessionFiles(Path(data_dir)))
    try:
        result = JOB_KINDS[kind](ctx)
    except Exception as exc:  # a job's failure is recorded, never raised into the runner
        log.error("job %d (%s) failed:\n%s", job_id, kind, traceback.format_exc())
        _finish(factory, job_id, JobState.failed, error=f"{type(exc).__name__}: {exc}")
        return
    _finish(factory, job_id, JobState.done, result=result)


def _finish(factory: sessionmaker[Session], job_id: int, state: JobState, *, error: str | None = None, result: dict[str, Any] | None = None) -> None:
    with factory() as db:
        job = db.get(Job, job_id)
        if job is None:
            return
        job.state, job.finished_at, job.error = state, utcnow(), error
        if result is not None:
            job.result, job.progress = result, 1.0
        db.commit()


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"could not encode {path.name}")
    write_atomic(path, buf.tobytes())


def run_stitch(ctx: JobContext) -> dict[str, Any]:
    """Mosaic of the session's frames: odometry through the camera mount as the initial
    guess, every overlapping pair registered, poses solved globally, written as PNG, Deep
    Zoom pyramid, overview and world mapping with bounded memory."""
    calib = ctx.session().calibration.get("camera", {})
    px_per_m = float(calib.get("px_per_m", 0)) or None
    T_rc = calib.get("T_robot_camera", [0.0, 0.0, 0.0])
    with ctx.factory() as db:
        frames = list(db.scalars(select(Frame).where(Frame.session_id == ctx.session_id).order_by(Frame.seq)))
    if not frames:
        raise ValueError("the session has no camera frames")
    # frames of another size than most, or whose file is gone, are skipped and reported
    sizes = Counter((f.width, f.height) for f in frames)
    size = sizes.most_common(1)[0][0]
    use, skipped = [], []
    for f in frames:
        try:  # the header only: a frame that cannot be read is skipped, not fatal
            w, h, _ = image_header(ctx.files.payload(f), f"frame {f.seq}")
            ok = (w, h) == size
        except (ValueError, OSError):
            ok = False
        (use if ok else skipped).append(f)
    if not use:
        raise ValueError(f"none of the session's {len(frames)} frames could be read as an image")
    with_pose = all(f.pose_x is not None for f in use) and px_per_m is not None
    guess = None
    if with_pose and px_per_m is not None:
        robot = np.array([[f.pose_x, f.pose_y, f.pose_yaw] for f in use], dtype=np.float64)
        guess = camera_poses(robot, T_rc, px_per_m)
    source = StoredImages(lambda k: ctx.files.payload(use[k]), len(use))
    layout, loaded = plan_mosaic(source, guess, px_per_m=px_per_m if with_pose and px_per_m else 1.0,
                                 progress=lambda f, m: ctx.progress(0.7 * f, m))
    out = ctx.results_dir()
    world = {"world_referenced": with_pose, "frames": frame_records(layout, [f.seq for f in use]), "skipped_frames": [f.seq for f in skipped]}
    files = write_mosaic(out, layout, render_bands(layout, loaded, progress=lambda f, m: ctx.progress(0.7 + 0.25 * f, m)), world=world)
    return {"mosaic_path": str(files.mosaic), "overview_path": str(files.overview), "dzi_path": str(files.dzi) if files.dzi else None,
            "width_px": layout.width, "height_px": layout.height, "px_per_m": layout.px_per_m, "origin_m": list(layout.origin_m),
            "world_referenced": with_pose, "frames": len(use), "skipped_frames": [f.seq for f in skipped],
            "low_confidence_frames": int((~layout.confident).sum()), "pairs": layout.pairs, "rejected_pairs": layout.rejected_pairs,
            "overview_scale": files.overview_scale, "params": params_record(StitchParams())}


def run_map(ctx: JobContext) -> dict[str, Any]:
    """3D map from the session's ToF clouds: odometry-seeded point-to-plane ICP."""
    import open3d as o3d

    calib = ctx.session().calibration.get("tof", {})
    T_rt = np.array(calib.get("T_robot_tof", np.eye(4).tolist()), dtype=np.float64)
    with ctx.factory() as db:
        rows = list(db.scalars(select(Cloud).where(Cloud.session_id == ctx.session_id).order_by(Cloud.seq)))
    if not rows:
        raise ValueError("the session has no ToF clouds")
    clouds, guesses, stamps, seqs, skipped = [], [], [], [], []
    shapes = {(c.height, c.width) for c in rows}
    shape = shapes.pop() if len(shapes) == 1 else None  # organised depth images: filtered as images
    if shape is not None and min(shape) < 2:
        shape = None
    for i, c in enumerate(rows):
        meta = {"encoding": c.encoding, "width": c.width, "height": c.height, **c.intrinsics}
        try:
            pts = decode_cloud(ctx.files.payload(c), meta)
        except (OSError, ValueError):
            skipped.append(c.seq)
            continue
        if not np.isfinite(pts).all(axis=1).any():
            skipped.append(c.seq)
            continue
        clouds.append(pts)
        stamps.append(c.timestamp)
        seqs.append(c.seq)
        if c.pose_x is not None:
            guesses.append(se2_to_se3(c.pose_x, c.pose_y, c.pose_yaw) @ T_rt)
        if i % 10 == 0:
            ctx.progress(0.3 * i / len(rows), f"decoded {i}/{len(rows)} clouds")
    if not clouds:
        raise ValueError("no readable ToF cloud in the session")
    params = MapParams()
    robot = _visual_robot_poses(ctx, rows, seqs) if len(guesses) == len(clouds) else None
    if robot is not None:
        # the mosaic's sub-pixel camera motion, carried over to the clouds, places them far
        # better than ICP on a mostly flat view can (0.03 mm against 3-5 mm on the simulator)
        guesses = [se2_to_se3(*p) @ T_rt for p in robot]
        params = MapParams(refine=False)
    ctx.progress(0.3, "registering")
    result = register_clouds(clouds, np.array(guesses) if len(guesses) == len(clouds) else None, params=params, shape=shape)
    out = ctx.results_dir()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(result.points.astype(np.float64)))
    tmp = out / ".map.tmp.ply"
    if not o3d.io.write_point_cloud(str(tmp), pcd):
        raise OSError("could not write map.ply")
    tmp.replace(out / "map.ply")
    write_atomic(out / "trajectory.tum", format_tum(np.array(stamps), result.poses).encode())
    return {"map_path": str(out / "map.ply"), "trajectory_path": str(out / "trajectory.tum"), "points": len(result.points),
            "guided_by_mosaic": robot is not None, "loop_closures": result.loop_closures,
            "clouds": len(clouds), "skipped_clouds": skipped, "cloud_seqs": seqs, "odometry_fallbacks": int(result.used_odometry.sum()),
            # clouds whose view left some directions to the odometry (a flat plate: sliding along it)
            "clouds_with_unobservable_directions": int((result.degenerate_dims > 0).sum()),
            # the odometry's heading error measured against ICP, over the configured one (1: as configured)
            "odometry_error_scale": round(result.odometry_error_scale, 2),
            "plane_landmarks": result.plane_landmarks,  # large planes (deck plate, web) tying the clouds that see them
            "mean_fitness": float(result.fitness.mean()), "params": params_record(params)}


def _visual_robot_poses(ctx: JobContext, clouds: list[Cloud], seqs: list[int]) -> NDArray[np.float64] | None:
    """Robot poses at the clouds' times from the mosaic (when the stitch job placed the frames
    on the structure by image registration), else None."""
    world_file = ctx.results_dir() / "mosaic.json"
    calib = ctx.session().calibration.get("camera", {})
    if not world_file.is_file() or "T_robot_camera" not in calib:
        return None
    world = json.loads(world_file.read_text())
    if not world.get("world_referenced"):
        return None
    placed = {f["frame"]: f for f in world.get("frames", []) if f.get("confident")}
    with ctx.factory() as db:
        frames = [f for f in db.scalars(select(Frame).where(Frame.session_id == ctx.session_id).order_by(Frame.seq))
                  if f.seq in placed and f.pose_x is not None]
    if len(frames) < 2:
        return None
    ox, oy = world["origin_m"]
    scale = float(world["px_per_m"])
    mount_inv = np.linalg.inv(se2_matrix(*calib["T_robot_camera"]))
    visual, odometry, times = [], [], []
    for f in frames:
        p = placed[f.seq]
        cam = se2_matrix(ox + p["x"] / scale, oy + p["y"] / scale, np.radians(p["theta_deg"]))
        M = cam @ mount_inv
        visual.append([M[0, 2], M[1, 2], np.arctan2(M[1, 0], M[0, 0])])
        odometry.append([f.pose_x, f.pose_y, f.pose_yaw])
        times.append(f.timestamp)
    by_seq = {c.seq: c for c in clouds}
    cloud_times = np.array([by_seq[s].timestamp for s in seqs])
    cloud_odo = np.array([[by_seq[s].pose_x, by_seq[s].pose_y, by_seq[s].pose_yaw] for s in seqs])
    return transfer_correction(np.array(times), np.array(odometry), np.array(visual), cloud_times, cloud_odo)


def _defect_row(ctx: JobContext, d: Defect_, source: str, mm: bool, world: tuple[float, float, float, float] | None,
                frame_seq: int | None = None) -> Defect:
    x, y, w, h = d.bbox
    wx, wy, ww, wh = world if world is not None else (None, None, None, None)
    return Defect(
        session_id=ctx.session_id, job_id=ctx.job_id, source=source, frame_seq=frame_seq, defect_class=d.defect_class,
        bbox_x=x, bbox_y=y, bbox_w=w, bbox_h=h, area_px=d.area_px, length_px=d.length_px,
        max_width_px=d.max_width_px, mean_width_px=d.mean_width_px, orientation_deg=d.orientation_deg,
        length_mm=d.length_mm if mm else None, max_width_mm=d.max_width_mm if mm else None,
        area_mm2=d.area_mm2 if mm else None, world_x_m=wx, world_y_m=wy, world_w_m=ww, world_h_m=wh,
    )


def _detect_in(image: np.ndarray, mm_per_px: float | None, valid: np.ndarray | None = None,
               seams: np.ndarray | None = None, workers: int = 2) -> tuple[np.ndarray, np.ndarray, list[Defect_]]:
    """Crack and rust masks of one image and its measured defects."""
    masks = defect_masks(image, valid, seams, workers=workers)
    with ThreadPoolExecutor(max_workers=workers) as pool:  # labelling and distances release the GIL
        rust = pool.submit(measure_defects, masks.rust, "corrosion", mm_per_px=mm_per_px, components=masks.rust_components)
        found = measure_defects(masks.cracks, "crack", mm_per_px=mm_per_px, contrast=masks.contrast,
                                components=masks.crack_components)
        found += [replace(d, id=len(found) + d.id) for d in rust.result()]
    return masks.cracks, masks.rust, found


def _detect_frames(ctx: JobContext) -> list[Defect]:
    """Defects of every camera frame, placed on the structure through the frame's pose."""
    calib = ctx.session().calibration.get("camera", {})
    px_per_m = float(calib.get("px_per_m", 0)) or None
    T_rc = np.array(calib.get("T_robot_camera", [0.0, 0.0, 0.0]))
    with ctx.factory() as db:
        frames = list(db.scalars(select(Frame).where(Frame.session_id == ctx.session_id).order_by(Frame.seq)))
    mm_per_px = 1000.0 / px_per_m if px_per_m else None

    def detect(f: Frame) -> tuple[tuple[int, int], list[Defect_]] | None:
        try:
            img = cv2.imdecode(np.frombuffer(ctx.files.payload(f), np.uint8), cv2.IMREAD_COLOR)
        except OSError:
            return None
        if img is None:
            return None
        return (img.shape[1], img.shape[0]), _detect_in(img, mm_per_px, workers=1)[2]

    rows: list[Defect] = []
    with ThreadPoolExecutor(max_workers=2) as pool:  # a frame per core: decoding and detection release the GIL
        for i, (f, done) in enumerate(zip(frames, pool.map(detect, frames))):
            if i % 10 == 0:
                ctx.progress(0.5 * i / max(len(frames), 1), f"frames {i}/{len(frames)}")
            if done is not None:
                rows += _frame_rows(ctx, f, done[1], done[0], px_per_m, T_rc)
    return rows


def _frame_rows(ctx: JobContext, f: Frame, found: list[Defect_], size: tuple[int, int], px_per_m: float | None,
                T_rc: NDArray[np.float64]) -> list[Defect]:
    """Rows of one frame's defects, placed on the structure through the frame's pose."""
    rows: list[Defect] = []
    cam = compose_se2(np.array([f.pose_x, f.pose_y, f.pose_yaw]), T_rc) if px_per_m and f.pose_x is not None else None
    for d in found:
        world = None
        if cam is not None:
            x, y, w, h = d.bbox
            corners = image_to_world(np.array([[x, y], [x + w, y], [x, y + h], [x + w, y + h]]), cam, px_per_m, size)
            lo, hi = corners.min(axis=0), corners.max(axis=0)
            world = (float(lo[0]), float(lo[1]), float(hi[0] - lo[0]), float(hi[1] - lo[1]))
        rows.append(_defect_row(ctx, d, "frame", px_per_m is not None, world, frame_seq=f.seq))
    return rows


def run_detect(ctx: JobContext) -> dict[str, Any]:
    """Cracks and corrosion in every frame and on the mosaic, measured and placed on the structure."""
    frame_rows = _detect_frames(ctx)
    out = ctx.results_dir()
    if not (out / "mosaic.png").is_file() or not (out / "mosaic.json").is_file():
        raise ValueError("no mosaic to run detection on: run the stitch job first")
    world = json.loads((out / "mosaic.json").read_text())
    px_per_m, (ox, oy) = world["px_per_m"], world["origin_m"]
    referenced = bool(world.get("world_referenced"))
    mm_per_px = 1000.0 / px_per_m if referenced else None
    ctx.progress(0.6, "mosaic")
    if int(world["width_px"]) * int(world["height_px"]) > MOSAIC_IN_MEMORY_PX:
        found = _detect_mosaic_banded(ctx, out, mm_per_px)
    else:
        found = _detect_mosaic(out, mm_per_px)
    mosaic_rows = []
    for d in found:
        x, y, w, h = d.bbox
        placed = (ox + x / px_per_m, oy + y / px_per_m, w / px_per_m, h / px_per_m) if referenced else None
        mosaic_rows.append(_defect_row(ctx, d, "mosaic", referenced, placed))
    with ctx.factory() as db:
        reviewed = list(db.scalars(select(Defect).where(Defect.session_id == ctx.session_id, Defect.reviewed_by.is_not(None))))
        kept = carry_reviews(reviewed, frame_rows + mosaic_rows)
        db.execute(delete(Defect).where(Defect.session_id == ctx.session_id))
        db.add_all(frame_rows + mosaic_rows)
        db.commit()
    by_class = {c: sum(1 for d in found if d.defect_class == c) for c in ("crack", "corrosion")}
    return {"defects": len(found), "by_class": by_class, "frame_defects": len(frame_rows), "method": "proposed",
            "reviews_carried_over": kept, "crack_mask": str(out / "crack_mask.png"), "params": {"crack": params_record(CrackParams()), "corrosion": params_record(CorrosionParams())}}


def _detect_mosaic(out: Path, mm_per_px: float | None) -> list[Defect_]:
    """Defects of a mosaic that fits in memory, found in one pass; writes the mask PNGs."""
    mosaic = cv2.imread(str(out / "mosaic.png"), cv2.IMREAD_COLOR)
    if mosaic is None:
        raise ValueError("mosaic.png cannot be read")
    coverage = cv2.imread(str(out / "mosaic_coverage.png"), cv2.IMREAD_GRAYSCALE)
    if coverage is None or coverage.shape != mosaic.shape[:2]:
        coverage = np.any(mosaic > 0, axis=2).astype(np.uint8) * 255
    seams = cv2.imread(str(out / "mosaic_seams.png"), cv2.IMREAD_GRAYSCALE) if (out / "mosaic_seams.png").is_file() else None
    seams = seams > 0 if seams is not None and seams.shape == mosaic.shape[:2] else None
    cracks, rust, found = _detect_in(mosaic, mm_per_px, on_surface(mosaic, coverage), seams)
    _write_png(out / "crack_mask.png", cracks.astype(np.uint8) * 255)
    _write_png(out / "corrosion_mask.png", rust.astype(np.uint8) * 255)
    return found


def _detect_mosaic_banded(ctx: JobContext, out: Path, mm_per_px: float | None) -> list[Defect_]:
    """Defects of a mosaic too large for memory, band by band (:mod:`server.jobs.banded`);
    the surface's brightness level comes from the overview."""
    from server.jobs.banded import detect_banded

    overview = cv2.imread(str(out / "mosaic_overview.png"), cv2.IMREAD_COLOR)
    if overview is None:
        raise ValueError("mosaic_overview.png cannot be read")
    level = surface_level(overview, np.any(overview > 0, axis=2))
    return detect_banded(out, defect_masks, mm_per_px, level, progress=lambda f, m: ctx.progress(0.6 + 0.35 * f, m))


def run_export(ctx: JobContext) -> dict[str, Any]:
    """The whole session as an MCAP file (``results/session.mcap``), written under a temporary
    name and renamed when complete."""
    from server.reports.mcap_export import export_session

    out = ctx.results_dir()
    tmp = out / f".session.mcap.{ctx.job_id}.tmp"
    try:
        with ctx.factory() as db, tmp.open("wb") as fh:
            counts = export_session(db, ctx.files, ctx.session_id, fh, progress=ctx.progress)
        tmp.replace(out / "session.mcap")
    finally:
        tmp.unlink(missing_ok=True)
    return {"mcap_path": str(out / "session.mcap"), "bytes": (out / "session.mcap").stat().st_size, **counts}


def _box_iou(a: Defect, b: Defect) -> float:
    x0, y0 = max(a.bbox_x, b.bbox_x), max(a.bbox_y, b.bbox_y)
    x1, y1 = min(a.bbox_x + a.bbox_w, b.bbox_x + b.bbox_w), min(a.bbox_y + a.bbox_h, b.bbox_y + b.bbox_h)
    inter = max(0, x1 - x0) * max(0, y1 - y0)
    union = a.bbox_w * a.bbox_h + b.bbox_w * b.bbox_h - inter
    return inter / union if union > 0 else 0.0


def carry_reviews(reviewed: list[Defect], new: list[Defect], min_iou: float = 0.3) -> int:
    """Give each new defect the review of the reviewed old one it overlaps most (same
    class, source and frame, box IoU ≥ ``min_iou``): re-running detection keeps the
    inspectors' work. Returns how many reviews were carried over."""
    carried = 0
    for d in new:
        same = [r for r in reviewed if (r.defect_class, r.source, r.frame_seq) == (d.defect_class, d.source, d.frame_seq)]
        best = max(same, key=lambda r: _box_iou(r, d), default=None)
        if best is not None and _box_iou(best, d) >= min_iou:
            d.review_status, d.condition_state, d.comment = best.review_status, best.condition_state, best.comment
            d.reviewed_by, d.reviewed_at = best.reviewed_by, best.reviewed_at
            carried += 1
    return carried


def params_record(params: Any) -> dict[str, Any]:
    """A parameters dataclass as JSON-ready data (for the report's parameter table)."""
    return json.loads(json.dumps(asdict(params), default=str))


JOB_KINDS: dict[str, Callable[[JobContext], dict[str, Any]]] = {"stitch": run_stitch, "map": run_map, "detect": run_detect,
                                                               "export": run_export}
