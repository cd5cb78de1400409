"""File-based commands (detect, stitch; map: :mod:`server.cli.map_command`): read inputs, call ``processing``, write outputs.

Every output is written atomically, so a failed command leaves no half-written file.
"""

from __future__ import annotations

import csv
import io
import json
import logging
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from processing.detection import detect_cracks, detect_cracks_tiled
from processing.detection.defects import measure_defects
from processing.poses import yaw_of
from processing.stitching import plan_mosaic, render_bands
from server.cli.inputs import list_files, read_odometry
from server.errors import CommandError
from server.storage.files import write_atomic
from server.storage.mosaic_files import ImageFiles, frame_records, image_header, write_mosaic

log = logging.getLogger(__name__)

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}
TILED_ABOVE_PX = 4_000_000
EIGHT_BIT_MODES = {"L", "P", "RGB", "RGBA", "LA", "1"}


def read_image(path: Path) -> np.ndarray:
    if not path.is_file():
        raise CommandError(f"{path}: no such file")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CommandError(f"{path}: not an image OpenCV can read")
    return img


def _png(image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise CommandError("could not encode PNG")
    return buf.tobytes()


def detect_images(images: list[Path], out: Path, *, method: str, px_per_mm: float | None) -> None:
    """Write ``<stem>.png`` masks and ``defects.json`` for each image."""
    if px_per_mm is not None and px_per_mm <= 0:
        raise CommandError(f"--px-per-mm must be positive, got {px_per_mm}")
    loaded = [(p, read_image(p)) for p in images]  # read all first: bad input writes nothing
    out.mkdir(parents=True, exist_ok=True)
    records = []
    for path, img in loaded:
        try:
            # large images (mosaics) go tile by tile on both cores with bounded working memory
            big = img.shape[0] * img.shape[1] > TILED_ABOVE_PX
            mask = (
                detect_cracks_tiled(img, method=method)
                if big
                else detect_cracks(img, method=method)
            )  # type: ignore[arg-type]
        except (ValueError, FileNotFoundError) as exc:
            raise CommandError(f"{path}: {exc}") from None
        mm_per_px = 1.0 / px_per_mm if px_per_mm else None
        for d in measure_defects(mask, "crack", mm_per_px=mm_per_px, first_id=len(records) + 1):
            rec = {"image": path.name, **{k: v for k, v in asdict(d).items() if v is not None}}
            rec["bbox"] = list(d.bbox)
            records.append(rec)
        write_atomic(out / f"{path.stem}.png", _png(mask.astype(np.uint8) * 255))
    write_atomic(out / "defects.json", json.dumps(records, indent=1).encode())


def stitch_folder(
    frames_dir: Path, out: Path, *, odometry: Path | None, px_per_m: float | None
) -> None:
    """Write ``mosaic.png``, ``poses.csv``, the Deep Zoom pyramid, an overview and the world
    mapping (``mosaic.json``) for a folder of frames, reading the frames as needed."""
    files = list_files(frames_dir, IMAGE_EXTS, "image")
    if px_per_m is not None and px_per_m <= 0:
        raise CommandError(f"--px-per-m must be positive, got {px_per_m}")
    first: tuple[int, int] | None = None
    for p in files:  # headers only: bad input is refused before any work
        try:
            w, h, mode = image_header(p)
        except ValueError as exc:
            raise CommandError(str(exc)) from None
        if mode not in EIGHT_BIT_MODES:
            raise CommandError(f"{p}: expected an 8-bit image, got mode {mode}")
        if first is not None and (w, h) != first:
            raise CommandError(
                f"{p}: size {w}x{h} differs from the first frame's {first[0]}x{first[1]}"
            )
        first = first or (w, h)
    guess = None
    if odometry is not None:
        if not px_per_m:
            raise CommandError("--odometry needs --px-per-m (the image scale)")
        T = read_odometry(odometry, len(files), "frames")
        guess = np.array([[t[0, 3] * px_per_m, t[1, 3] * px_per_m, yaw_of(t)] for t in T])
    try:
        layout, frames = plan_mosaic(ImageFiles(files), guess, px_per_m=px_per_m or 1.0)
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["frame", "x", "y", "theta_deg"])
        for p, (x, y, th) in zip(files, layout.poses_px):
            w.writerow([p.name, f"{x:.3f}", f"{y:.3f}", f"{np.degrees(th):.4f}"])
        world = {
            "world_referenced": odometry is not None,
            "frames": frame_records(layout, [p.name for p in files]),
        }
        write_mosaic(out, layout, render_bands(layout, frames), world=world)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    write_atomic(out / "poses.csv", buf.getvalue().encode())
