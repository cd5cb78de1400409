"""An MCAP session file written by :mod:`server.reports.mcap_export` read back as a new session.

A broken or foreign file is refused (:class:`McapImportError`) and leaves nothing behind.
"""

from __future__ import annotations

import json
import math
import shutil
import struct
import uuid
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import zstandard
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from google.protobuf.message import DecodeError
from mcap.exceptions import McapError
from mcap.records import Metadata
from sqlalchemy import update
from sqlalchemy.exc import StatementError
from sqlalchemy.orm import Session

from robot_link.image_header import ImageHeaderError, check_pixels, png_header
from robot_link.protocol import MAX_CLOUD_PIXELS, MAX_FRAME_PIXELS
from server.reports.fields import IMPORTED_FROM
from server.reports.mcap_common import METADATA, Progress
from server.reports.mcap_records import ChunkError, messages
from server.storage.files import SessionFiles
from server.storage.models import (
    Cloud,
    Frame,
    InspectionSession,
    SessionStatus,
    TelemetrySample,
)


class McapImportError(ValueError):
    """The file is not an MCAP session this station can import."""


def import_session(
    db: Session, files: SessionFiles, path: Path, *, progress: Progress = lambda f, m: None
) -> dict[str, Any]:
    """Read an MCAP written by :func:`export_session` into a new session (frames and clouds
    byte for byte, telemetry, poses, calibration); nothing is left behind when it fails."""
    session_id = str(uuid.uuid4())
    try:
        with path.open("rb") as fh:
            meta, poses, calibration, depth_seqs = _first_pass(fh)
            db.add(_new_session(session_id, meta, path.name))
            db.flush()
            fh.seek(0)
            counts = _second_pass(db, files, session_id, fh, depth_seqs, calibration, progress)
        for model, topic in ((Frame, "/camera/odometry"), (Cloud, "/tof/odometry")):
            for seq, (x, y, yaw) in poses[topic].items():
                db.execute(
                    update(model)
                    .where(model.session_id == session_id, model.seq == seq)
                    .values(pose_x=x, pose_y=y, pose_yaw=yaw)
                )
        if not any(counts.values()):
            raise McapImportError(
                "the file holds no camera frames, clouds or telemetry on steelscan's topics"
            )
        db.commit()
    except McapImportError:
        _discard(db, files, session_id)
        raise
    except (
        McapError,
        ChunkError,
        zstandard.ZstdError,
        RuntimeError,  # lz4's errors
        DecodeError,
        EOFError,
        KeyError,
        IndexError,
        struct.error,
        ValueError,  # JSON, numbers and text that do not parse
        TypeError,
        OverflowError,
        RecursionError,  # JSON nested too deeply
        StatementError,  # a value the database refuses
    ) as exc:
        _discard(db, files, session_id)
        raise McapImportError(
            f"{path.name}: not a readable MCAP session ({type(exc).__name__}: {exc})"
        ) from None
    except BaseException:
        _discard(db, files, session_id)
        raise
    return {"session_id": session_id, **counts}


def _discard(db: Session, files: SessionFiles, session_id: str) -> None:
    db.rollback()
    shutil.rmtree(files.session_dir(session_id), ignore_errors=True)


def _new_session(session_id: str, meta: dict[str, str], name: str) -> InspectionSession:
    def when(key: str) -> datetime | None:
        try:
            return datetime.fromisoformat(meta[key]) if meta.get(key) else None
        except ValueError:
            return None

    try:
        calibration = json.loads(meta.get("calibration", "{}"))
    except ValueError:
        calibration = {}
    note = f"{IMPORTED_FROM} {name}" + (f" (session {meta['id']})" if meta.get("id") else "")
    return InspectionSession(
        id=session_id,
        robot_id=None,
        structure=meta.get("structure") or Path(name).stem,
        operator=meta.get("operator", ""),
        location=meta.get("location", ""),
        notes="\n".join(n for n in (meta.get("notes", ""), note) if n),
        status=SessionStatus.ended,
        started_at=when("started_at") or datetime.now(timezone.utc),
        ended_at=when("ended_at") or datetime.now(timezone.utc),
        end_reason=meta.get("end_reason") or "imported",
        calibration=calibration if isinstance(calibration, dict) else {},
    )


def _first_pass(
    fh: BinaryIO,
) -> tuple[
    dict[str, str],
    dict[str, dict[int, tuple[float, float, float]]],
    dict[int, dict[str, float]],
    set[int],
]:
    """Session metadata, odometry and calibration per sequence number, clouds sent as depth PNG."""
    meta: dict[str, str] = {}
    poses: dict[str, dict[int, tuple[float, float, float]]] = {
        "/camera/odometry": {},
        "/tof/odometry": {},
    }
    calibration: dict[int, dict[str, float]] = {}
    depth: set[int] = set()
    for item in messages(
        fh, {"/camera/odometry", "/tof/odometry", "/tof/calibration", "/tof/depth"}
    ):
        if isinstance(item, Metadata):
            if item.name == METADATA:
                meta = dict(item.metadata)
            continue
        channel, message = item
        if channel.topic == "/tof/depth":
            depth.add(message.sequence)
        elif channel.topic == "/tof/calibration":
            cal = CameraCalibration.FromString(message.data)
            entry = {"width": cal.width, "height": cal.height}
            if len(cal.K) == 9 and cal.K[0] > 0 and cal.K[4] > 0:
                entry |= {"fx": cal.K[0], "fy": cal.K[4], "cx": cal.K[2], "cy": cal.K[5]}
            calibration[message.sequence] = entry
        else:
            p = PoseInFrame.FromString(message.data).pose
            yaw = 2.0 * float(np.arctan2(p.orientation.z, p.orientation.w))
            poses[channel.topic][message.sequence] = (
                p.position.x,
                p.position.y,
                float(np.arctan2(np.sin(yaw), np.cos(yaw))),
            )
    return meta, poses, calibration, depth


def _second_pass(
    db: Session,
    files: SessionFiles,
    session_id: str,
    fh: BinaryIO,
    depth_seqs: set[int],
    calibration: dict[int, dict[str, float]],
    progress: Progress,
) -> dict[str, int]:
    counts = {"frames": 0, "clouds": 0, "telemetry": 0}
    seen: set[tuple[str, int]] = set()
    topics = {"/camera/image", "/tof/depth", "/tof/points", "/robot/telemetry"}
    for i, item in enumerate(messages(fh, topics)):
        if isinstance(item, Metadata):
            continue
        channel, m = item
        topic, seq, t = channel.topic, m.sequence, m.log_time / 1e9
        if topic == "/camera/image":
            img = CompressedImage.FromString(m.data)
            if ("frame", seq) in seen:
                continue
            seen.add(("frame", seq))
            rel = files.frame_relpath(session_id, seq)
            files.write(rel, img.data)
            w, h = _image_size(img.data, MAX_FRAME_PIXELS)
            db.add(
                Frame(
                    session_id=session_id,
                    seq=seq,
                    timestamp=img.timestamp.ToNanoseconds() / 1e9 or t,
                    width=w,
                    height=h,
                    path=rel,
                    size_bytes=len(img.data),
                )
            )
            counts["frames"] += 1
        elif topic == "/tof/depth" or (topic == "/tof/points" and seq not in depth_seqs):
            if ("cloud", seq) in seen:
                continue
            seen.add(("cloud", seq))
            db.add(_cloud_row(files, session_id, seq, topic, m.data, calibration.get(seq, {})))
            counts["clouds"] += 1
        elif topic == "/robot/telemetry":
            data = json.loads(m.data)
            if not isinstance(data, dict) or ("telemetry", seq) in seen:
                continue
            seen.add(("telemetry", seq))
            stamp = float(data.pop("timestamp", t))
            if not math.isfinite(stamp):
                raise McapImportError(f"telemetry {seq} has the timestamp {stamp}")
            db.add(TelemetrySample(session_id=session_id, seq=seq, timestamp=stamp, data=data))
            counts["telemetry"] += 1
        if i % 500 == 499:
            db.flush()
            progress(0.0, f"{i + 1} messages read")
    db.flush()
    return counts


def _cloud_row(
    files: SessionFiles, session_id: str, seq: int, topic: str, data: bytes, cal: dict[str, float]
) -> Cloud:
    intrinsics = {k: cal[k] for k in ("fx", "fy", "cx", "cy") if k in cal}
    if topic == "/tof/depth":
        img = CompressedImage.FromString(data)
        payload, encoding, t = img.data, "png16_depth_mm", img.timestamp.ToNanoseconds() / 1e9
        w, h = _image_size(payload, MAX_CLOUD_PIXELS, depth=True)
        if len(intrinsics) < 4:
            raise McapImportError(f"depth image {seq} has no intrinsics on /tof/calibration")
    else:
        cloud = PointCloud.FromString(data)
        fields = [(f.name, f.offset, f.type) for f in cloud.fields][:3]
        if cloud.point_stride != 12 or fields != [
            (n, 4 * i, PackedElementField.FLOAT32) for i, n in enumerate("xyz")
        ]:
            raise McapImportError(f"cloud {seq} is not packed float32 x, y, z")
        payload, encoding, t = cloud.data, "xyz_f32", cloud.timestamp.ToNanoseconds() / 1e9
        count = len(payload) // 12
        if count > MAX_CLOUD_PIXELS:
            raise McapImportError(
                f"cloud {seq} has {count:,} points, more than the {MAX_CLOUD_PIXELS:,} allowed"
            )
        w, h = int(cal.get("width", 0)), int(cal.get("height", 0))
        if w * h != count:
            w, h = count, 1
    rel = files.cloud_relpath(session_id, seq, encoding)
    files.write(rel, payload)
    return Cloud(
        session_id=session_id,
        seq=seq,
        timestamp=t,
        encoding=encoding,
        width=w,
        height=h,
        intrinsics=intrinsics,
        path=rel,
        size_bytes=len(payload),
    )


def _image_size(data: bytes, max_pixels: int, depth: bool = False) -> tuple[int, int]:
    """(width, height) of an encoded image from its header, refused before decoding when
    larger than ``max_pixels`` (or, for ``depth``, not a 16-bit greyscale PNG)."""
    try:
        if depth:
            png = png_header(data)
            if (png.bit_depth, png.colour_type) != (16, 0):
                raise ImageHeaderError("a depth image must be a 16-bit greyscale PNG")
        return check_pixels(data, max_pixels)
    except ImageHeaderError as exc:
        raise McapImportError(f"an image in the file is not usable: {exc}") from None
