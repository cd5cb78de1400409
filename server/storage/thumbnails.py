"""Defect thumbnails: the defect's neighbourhood cut from its frame or the mosaic, its box drawn."""

from __future__ import annotations

import cv2
import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.errors import NotFound
from server.storage.files import SessionFiles
from server.storage.models import Defect, Frame
from server.storage.mosaic_files import read_region

BOX_BGR = (40, 40, 230)
MIN_VIEW_PX = 96


def crop_box(x: int, y: int, w: int, h: int) -> tuple[int, int, int, int]:
    """A square window around a box, with a margin of half its size and at least MIN_VIEW_PX wide."""
    side = max(MIN_VIEW_PX, round(1.5 * max(w, h)))
    cx, cy = x + w / 2, y + h / 2
    return round(cx - side / 2), round(cy - side / 2), side, side


def defect_image(db: Session, files: SessionFiles, defect: Defect, size: int = 256) -> np.ndarray:
    """BGR thumbnail (longest side ``size``) of a defect with its bounding box outlined."""
    wx, wy, ww, wh = crop_box(defect.bbox_x, defect.bbox_y, defect.bbox_w, defect.bbox_h)
    if defect.source == "frame":
        frame = db.scalar(
            select(Frame).where(
                Frame.session_id == defect.session_id, Frame.seq == defect.frame_seq
            )
        )
        try:
            image = (
                cv2.imdecode(np.frombuffer(files.payload(frame), np.uint8), cv2.IMREAD_COLOR)
                if frame is not None
                else None
            )
        except OSError:
            image = None
        if image is None:
            raise NotFound(f"the frame of defect {defect.id} is gone or unreadable")
        crop, (ox, oy) = _cut(image, wx, wy, ww, wh)
    else:
        results = files.results_dir(defect.session_id)
        if not (results / "mosaic.json").is_file():
            raise NotFound(f"the mosaic of defect {defect.id} is gone")
        try:
            crop = read_region(results, wx, wy, ww, wh)
        except (ValueError, OSError) as exc:
            raise NotFound(f"cannot read the mosaic around defect {defect.id}: {exc}") from None
        ox, oy = max(0, wx), max(0, wy)
    scale = size / max(crop.shape[:2])
    thumb = cv2.resize(
        crop,
        (max(1, round(crop.shape[1] * scale)), max(1, round(crop.shape[0] * scale))),
        interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR,
    )
    p0 = (round((defect.bbox_x - ox) * scale) - 2, round((defect.bbox_y - oy) * scale) - 2)
    p1 = (
        round((defect.bbox_x + defect.bbox_w - ox) * scale) + 2,
        round((defect.bbox_y + defect.bbox_h - oy) * scale) + 2,
    )
    cv2.rectangle(thumb, p0, p1, BOX_BGR, 2)
    return thumb


def _cut(image: np.ndarray, x: int, y: int, w: int, h: int) -> tuple[np.ndarray, tuple[int, int]]:
    x0, y0 = max(0, x), max(0, y)
    x1, y1 = min(image.shape[1], x + w), min(image.shape[0], y + h)
    if x1 <= x0 or y1 <= y0:
        raise NotFound("the defect's box lies outside its image")
    return image[y0:y1, x0:x1], (x0, y0)


def encode_jpeg(image: np.ndarray, quality: int = 88) -> bytes:
    """JPEG bytes of a BGR image."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("could not encode the thumbnail")
    return buf.tobytes()
