"""The ``stitch`` job: the session's frames as a mosaic in world coordinates."""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
from sqlalchemy import select

from processing.stitching import StitchParams, camera_poses, plan_mosaic, render_bands
from server.jobs.context import JobContext, params_record
from server.storage.models import Frame
from server.storage.mosaic_files import (
    StoredImages,
    decodes,
    frame_records,
    image_header,
    write_mosaic,
)


def run_stitch(ctx: JobContext) -> dict[str, Any]:
    """Mosaic of the session's frames: odometry through the camera mount as the initial
    guess, every overlapping pair registered, poses solved globally, written as PNG, Deep
    Zoom pyramid, overview and world mapping with bounded memory."""
    calib = ctx.session().calibration.get("camera", {})
    px_per_m = float(calib.get("px_per_m", 0)) or None
    T_rc = calib.get("T_robot_camera", [0.0, 0.0, 0.0])
    with ctx.factory() as db:
        frames = list(
            db.scalars(select(Frame).where(Frame.session_id == ctx.session_id).order_by(Frame.seq))
        )
    if not frames:
        raise ValueError("the session has no camera frames")
    # frames of another size than most, whose file is gone or whose image data is corrupt
    # are skipped and reported
    sizes = Counter((f.width, f.height) for f in frames)
    size = sizes.most_common(1)[0][0]
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
    with_pose = all(f.pose_x is not None for f in use) and px_per_m is not None
    guess = None
    if with_pose and px_per_m is not None:
        robot = np.array([[f.pose_x, f.pose_y, f.pose_yaw] for f in use], dtype=np.float64)
        guess = camera_poses(robot, T_rc, px_per_m)
    source = StoredImages(lambda k: ctx.files.payload(use[k]), len(use))
    layout, loaded = plan_mosaic(
        source,
        guess,
        px_per_m=px_per_m if with_pose and px_per_m else 1.0,
        progress=lambda f, m: ctx.progress(0.7 * f, m),
    )
    out = ctx.results_dir()
    world = {
        "world_referenced": with_pose,
        "frames": frame_records(layout, [f.seq for f in use]),
        "skipped_frames": [f.seq for f in skipped],
    }
    files = write_mosaic(
        out,
        layout,
        render_bands(layout, loaded, progress=lambda f, m: ctx.progress(0.7 + 0.25 * f, m)),
        world=world,
    )
    return {
        "mosaic_path": str(files.mosaic),
        "overview_path": str(files.overview),
        "dzi_path": str(files.dzi) if files.dzi else None,
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
        "params": params_record(StitchParams()),
    }
