"""A whole inspection session as an MCAP file with Foxglove schemas.

Export streams rows and files into the MCAP (nothing held whole in memory) in time order:

=========================  ==========================  ====================================
topic                      schema                      what
=========================  ==========================  ====================================
``/camera/image``          foxglove.CompressedImage    each frame's JPEG, bytes as received
``/camera/odometry``       foxglove.PoseInFrame        robot pose (world) when it was taken
``/tof/points``            foxglove.PointCloud         each cloud, organised (W×H, NaN = none)
``/tof/depth``             foxglove.CompressedImage    16-bit depth PNG (mm) as received
``/tof/calibration``       foxglove.CameraCalibration  the ToF intrinsics of each cloud
``/tof/odometry``          foxglove.PoseInFrame        robot pose when the cloud was taken
``/tf``                    foxglove.FrameTransform     world → base_link (telemetry), mounts
``/robot/telemetry``       JSON                        each telemetry sample as received
``/map/points``            foxglove.PointCloud         the registered map (world), once
``/map/trajectory``        foxglove.PosesInFrame       the map's sensor trajectory, once
``/inspection/defects``    JSON                        the detected and reviewed defects, once
``/inspection/defect_markers`` foxglove.SceneUpdate    a box and label per defect on the structure
=========================  ==========================  ====================================

Every message's MCAP ``sequence`` is the robot's sequence number, and the ``steelscan.session``
metadata record holds the session's cover fields and calibration, so the import
(:mod:`server.reports.mcap_import`) rebuilds a session with byte-identical frames and clouds.
"""

from __future__ import annotations

import heapq
import json
from collections.abc import Iterator
from datetime import datetime, timezone
from typing import Any, BinaryIO

import numpy as np
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.reports.fields import GENERATOR, defect_record
from server.reports.foxglove_messages import (
    Pose,
    Record,
    cloud_records,
    frame_records,
    matrix_quaternion,
    mount_records,
    ns,
    set_pose,
    telemetry_records,
    xyz_cloud,
)
from server.reports.mcap_common import JSON_SCHEMA, METADATA, Progress
from server.storage.files import SessionFiles
from server.storage.models import (
    Cloud,
    Defect,
    Frame,
    InspectionSession,
    TelemetrySample,
)


class _Channels:
    """Lazily registered MCAP channels, one per topic."""

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self.ids: dict[str, int] = {}
        self.schemas: dict[str, int] = {}

    def write(self, topic: str, message: Any, t: float, seq: int = 0) -> None:
        """Write one protobuf message (or a dict, as JSON) on ``topic`` at time ``t`` (s)."""
        if topic not in self.ids:
            if isinstance(message, dict):
                key = "json"
                if key not in self.schemas:
                    self.schemas[key] = self.writer.register_schema(
                        "steelscan.Json", "jsonschema", JSON_SCHEMA
                    )
                self.ids[topic] = self.writer.register_channel(topic, "json", self.schemas[key])
            else:
                key = type(message).DESCRIPTOR.full_name
                if key not in self.schemas:
                    self.schemas[key] = register_schema(self.writer, type(message))
                self.ids[topic] = self.writer.register_channel(topic, "protobuf", self.schemas[key])
        data = (
            json.dumps(message).encode()
            if isinstance(message, dict)
            else message.SerializeToString()
        )
        self.writer.add_message(
            self.ids[topic], log_time=ns(t), publish_time=ns(t), data=data, sequence=seq % 2**32
        )


def _rows(db: Session, model: Any, session_id: str) -> Iterator[tuple[float, int, str, Any]]:
    q = (
        select(model)
        .where(model.session_id == session_id)
        .order_by(model.seq)
        .execution_options(yield_per=200)
    )
    for row in db.scalars(q):
        yield row.timestamp, row.seq, model.__tablename__, row


def export_session(
    db: Session,
    files: SessionFiles,
    session_id: str,
    out: BinaryIO,
    *,
    progress: Progress = lambda f, m: None,
) -> dict[str, Any]:
    """Write a session as MCAP to the binary stream ``out``; counts of what was written and
    the seqs of clouds whose points could not be read (their bytes are written all the same)."""
    s = db.get(InspectionSession, session_id)
    if s is None:
        raise KeyError(session_id)
    writer = Writer(out, chunk_size=4 * 1024 * 1024, compression=CompressionType.ZSTD)
    writer.start(profile="", library=GENERATOR)
    ch = _Channels(writer)
    writer.add_metadata(METADATA, _session_metadata(s))
    t0 = s.started_at.timestamp()
    first = db.scalar(
        select(Frame.timestamp).where(Frame.session_id == session_id).order_by(Frame.seq).limit(1)
    )
    t_start = first if first is not None else t0
    _write_mounts(ch, s.calibration, t_start)
    total = (
        sum(
            db.query(m).filter(m.session_id == session_id).count()
            for m in (Frame, Cloud, TelemetrySample)
        )
        or 1
    )
    counts = {"frames": 0, "clouds": 0, "telemetry": 0}
    unreadable: list[int] = []
    merged = heapq.merge(
        _rows(db, Frame, session_id),
        _rows(db, Cloud, session_id),
        _rows(db, TelemetrySample, session_id),
        key=lambda r: (r[0], r[1]),
    )
    t_last = t_start
    for i, (t, seq, table, row) in enumerate(merged):
        t_last = max(t_last, t)
        if table == "frames":
            _write_frame(ch, files, row)
        elif table == "clouds":
            if not _write_cloud(ch, files, row):
                unreadable.append(seq)
        else:
            _write_telemetry(ch, row)
        counts[table] += 1
        if i % 200 == 0:
            progress(0.9 * i / total, f"{i}/{total} messages")
    _write_results(ch, db, files, session_id, t_last)
    writer.finish()
    return {**counts, "unreadable_clouds": unreadable}


def _session_metadata(s: InspectionSession) -> dict[str, str]:
    return {
        "id": s.id,
        "structure": s.structure,
        "operator": s.operator,
        "location": s.location,
        "notes": s.notes,
        "robot": s.robot.name if s.robot else "",
        "status": s.status.value,
        "end_reason": s.end_reason or "",
        "started_at": s.started_at.isoformat(),
        "ended_at": s.ended_at.isoformat() if s.ended_at else "",
        "calibration": json.dumps(s.calibration),
        "exported_at": datetime.now(timezone.utc).isoformat(),
        "generator": GENERATOR,
    }


def _write_mounts(ch: _Channels, calibration: dict[str, Any], t: float) -> None:
    _write_records(ch, mount_records(calibration, t), t)


def _write_records(ch: _Channels, records: list[Record], t: float, seq: int = 0) -> None:
    for topic, message in records:
        ch.write(topic, message, t, seq)


def _pose(row: Frame | Cloud) -> Pose | None:
    if row.pose_x is None:
        return None
    return row.pose_x, row.pose_y or 0.0, row.pose_yaw or 0.0


def _write_frame(ch: _Channels, files: SessionFiles, f: Frame) -> None:
    _write_records(ch, frame_records(files.payload(f), _pose(f), f.timestamp), f.timestamp, f.seq)


def _write_cloud(ch: _Channels, files: SessionFiles, c: Cloud) -> bool:
    """Write a cloud's pose, calibration, depth image and points; False when its payload
    cannot be read as a cloud (everything but the points is written)."""
    records, readable = cloud_records(
        files.payload(c), c.encoding, c.width, c.height, c.intrinsics, _pose(c), c.timestamp
    )
    _write_records(ch, records, c.timestamp, c.seq)
    return readable


def _write_telemetry(ch: _Channels, sample: TelemetrySample) -> None:
    records = telemetry_records(sample.data, sample.timestamp)
    _write_records(ch, records, sample.timestamp, sample.seq)


def _write_results(
    ch: _Channels, db: Session, files: SessionFiles, session_id: str, t: float
) -> None:
    from processing.poses import parse_tum
    from server.storage.ply import read_ply_points

    results = files.results_dir(session_id)
    try:
        ch.write("/map/points", xyz_cloud(read_ply_points(results / "map.ply"), "world", t), t)
    except (OSError, ValueError):
        pass
    try:
        _, poses = parse_tum((results / "trajectory.tum").read_text())
    except (OSError, ValueError):
        poses = np.empty((0, 4, 4))
    if len(poses):
        traj = PosesInFrame(frame_id="world")
        traj.timestamp.FromNanoseconds(ns(t))
        for T in poses:
            set_pose(
                traj.poses.add(), tuple(float(v) for v in T[:3, 3]), matrix_quaternion(T[:3, :3])
            )  # type: ignore[arg-type]
        ch.write("/map/trajectory", traj, t)
    defects = list(
        db.scalars(select(Defect).where(Defect.session_id == session_id).order_by(Defect.id))
    )
    if defects:
        ch.write("/inspection/defects", {"defects": [defect_record(d) for d in defects]}, t)
        placed = [d for d in defects if d.source == "mosaic" and d.world_x_m is not None]
        if placed:
            ch.write("/inspection/defect_markers", _defect_markers(placed, t), t)


def _defect_markers(defects: list[Defect], t: float) -> SceneUpdate:
    """A box and a label per defect on the structure (Foxglove's 3D panel shows them)."""
    update = SceneUpdate()
    for d in defects:
        entity = update.entities.add(frame_id="world", id=f"defect-{d.id}")
        entity.timestamp.FromNanoseconds(ns(t))
        red, green = (1.0, 0.23) if d.defect_class == "crack" else (1.0, 0.8)
        w, h = max(d.world_w_m or 0.0, 0.005), max(d.world_h_m or 0.0, 0.005)
        cube = entity.cubes.add()
        set_pose(cube.pose, (d.world_x_m + w / 2, d.world_y_m + h / 2, 0.0), (0.0, 0.0, 0.0, 1.0))
        cube.size.x, cube.size.y, cube.size.z = w, h, 0.004
        cube.color.r, cube.color.g, cube.color.b, cube.color.a = red, green, 0.2, 0.6
        label = entity.texts.add(
            billboard=True,
            font_size=14.0,
            scale_invariant=True,
            text=f"#{d.number or d.id} {d.defect_class} {d.length_mm or 0:.0f} mm {d.condition_state or ''}".strip(),
        )
        set_pose(label.pose, (d.world_x_m + w / 2, d.world_y_m + h / 2, 0.02), (0.0, 0.0, 0.0, 1.0))
        label.color.r = label.color.g = label.color.b = label.color.a = 1.0
    return update


# --------------------------------------------------------------------------- import
