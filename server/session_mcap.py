"""A whole inspection session as an MCAP file with Foxglove schemas, and back.

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
metadata record holds the session's cover fields and calibration, so :func:`import_session`
rebuilds a session with byte-identical frames and clouds.
"""

from __future__ import annotations

import heapq
import json
import shutil
import struct
import uuid
from collections.abc import Callable, Iterator
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.message import DecodeError
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from robot_link.clouds import decode_cloud
from server.models import Cloud, Defect, Frame, InspectionSession, SessionStatus, TelemetrySample
from server.report import GENERATOR
from server.storage import SessionFiles

METADATA = "steelscan.session"
FRAME_TOPICS = ("/camera/image", "/camera/odometry")
CLOUD_TOPICS = ("/tof/points", "/tof/depth", "/tof/calibration", "/tof/odometry")
JSON_SCHEMA = json.dumps({"type": "object"}).encode()
Progress = Callable[[float, str], None]


def _ns(t: float) -> int:
    return max(0, int(round(t * 1e9)))


def _yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    return 0.0, 0.0, float(np.sin(yaw / 2)), float(np.cos(yaw / 2))


def _matrix_quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return float(x), float(y), float(z), float(w)


def _set_pose(pose: Any, xyz: tuple[float, float, float], q: tuple[float, float, float, float]) -> None:
    pose.position.x, pose.position.y, pose.position.z = xyz
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = q


def _xyz_cloud(points: np.ndarray, frame_id: str, t: float) -> PointCloud:
    msg = PointCloud(frame_id=frame_id, point_stride=12, data=np.ascontiguousarray(points, dtype="<f4").tobytes())
    msg.timestamp.FromNanoseconds(_ns(t))
    msg.pose.orientation.w = 1.0
    for i, name in enumerate("xyz"):
        msg.fields.add(name=name, offset=4 * i, type=PackedElementField.FLOAT32)
    return msg


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
                    self.schemas[key] = self.writer.register_schema("steelscan.Json", "jsonschema", JSON_SCHEMA)
                self.ids[topic] = self.writer.register_channel(topic, "json", self.schemas[key])
            else:
                key = type(message).DESCRIPTOR.full_name
                if key not in self.schemas:
                    self.schemas[key] = register_schema(self.writer, type(message))
                self.ids[topic] = self.writer.register_channel(topic, "protobuf", self.schemas[key])
        data = json.dumps(message).encode() if isinstance(message, dict) else message.SerializeToString()
        self.writer.add_message(self.ids[topic], log_time=_ns(t), publish_time=_ns(t), data=data, sequence=seq % 2**32)


def _rows(db: Session, model: Any, session_id: str) -> Iterator[tuple[float, int, str, Any]]:
    q = select(model).where(model.session_id == session_id).order_by(model.seq).execution_options(yield_per=200)
    for row in db.scalars(q):
        yield row.timestamp, row.seq, model.__tablename__, row


def export_session(db: Session, files: SessionFiles, session_id: str, out: BinaryIO, *,
                   progress: Progress = lambda f, m: None) -> dict[str, int]:
    """Write a session as MCAP to the binary stream ``out``; counts of what was written."""
    s = db.get(InspectionSession, session_id)
    if s is None:
        raise KeyError(session_id)
    writer = Writer(out, chunk_size=4 * 1024 * 1024, compression=CompressionType.ZSTD)
    writer.start(profile="", library=GENERATOR)
    ch = _Channels(writer)
    writer.add_metadata(METADATA, _session_metadata(s))
    t0 = s.started_at.timestamp()
    first = db.scalar(select(Frame.timestamp).where(Frame.session_id == session_id).order_by(Frame.seq).limit(1))
    t_start = first if first is not None else t0
    _write_mounts(ch, s.calibration, t_start)
    total = sum(db.query(m).filter(m.session_id == session_id).count() for m in (Frame, Cloud, TelemetrySample)) or 1
    counts = {"frames": 0, "clouds": 0, "telemetry": 0}
    merged = heapq.merge(_rows(db, Frame, session_id), _rows(db, Cloud, session_id), _rows(db, TelemetrySample, session_id),
                         key=lambda r: (r[0], r[1]))
    t_last = t_start
    for i, (t, seq, table, row) in enumerate(merged):
        t_last = max(t_last, t)
        if table == "frames":
            _write_frame(ch, files, row)
        elif table == "clouds":
            _write_cloud(ch, files, row)
        else:
            _write_telemetry(ch, row)
        counts[table] += 1
        if i % 200 == 0:
            progress(0.9 * i / total, f"{i}/{total} messages")
    _write_results(ch, db, files, session_id, t_last)
    writer.finish()
    return counts


def _session_metadata(s: InspectionSession) -> dict[str, str]:
    return {"id": s.id, "structure": s.structure, "operator": s.operator, "location": s.location, "notes": s.notes,
            "robot": s.robot.name if s.robot else "", "status": s.status.value, "end_reason": s.end_reason or "",
            "started_at": s.started_at.isoformat(), "ended_at": s.ended_at.isoformat() if s.ended_at else "",
            "calibration": json.dumps(s.calibration), "exported_at": datetime.now(timezone.utc).isoformat(), "generator": GENERATOR}


def _write_mounts(ch: _Channels, calibration: dict[str, Any], t: float) -> None:
    cam = calibration.get("camera", {}).get("T_robot_camera")
    if cam is not None:
        tf = FrameTransform(parent_frame_id="base_link", child_frame_id="camera")
        tf.timestamp.FromNanoseconds(_ns(t))
        tf.translation.x, tf.translation.y = float(cam[0]), float(cam[1])
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = _yaw_quaternion(float(cam[2]))
        ch.write("/tf", tf, t)
    tof = calibration.get("tof", {}).get("T_robot_tof")
    if tof is not None:
        T = np.asarray(tof, dtype=np.float64)
        tf = FrameTransform(parent_frame_id="base_link", child_frame_id="tof")
        tf.timestamp.FromNanoseconds(_ns(t))
        tf.translation.x, tf.translation.y, tf.translation.z = (float(v) for v in T[:3, 3])
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = _matrix_quaternion(T[:3, :3])
        ch.write("/tf", tf, t)


def _write_pose(ch: _Channels, topic: str, row: Frame | Cloud) -> None:
    if row.pose_x is None:
        return
    msg = PoseInFrame(frame_id="world")
    msg.timestamp.FromNanoseconds(_ns(row.timestamp))
    _set_pose(msg.pose, (row.pose_x, row.pose_y or 0.0, 0.0), _yaw_quaternion(row.pose_yaw or 0.0))
    ch.write(topic, msg, row.timestamp, row.seq)


def _write_frame(ch: _Channels, files: SessionFiles, f: Frame) -> None:
    _write_pose(ch, "/camera/odometry", f)
    msg = CompressedImage(frame_id="camera", format="jpeg", data=files.payload(f))
    msg.timestamp.FromNanoseconds(_ns(f.timestamp))
    ch.write("/camera/image", msg, f.timestamp, f.seq)


def _write_cloud(ch: _Channels, files: SessionFiles, c: Cloud) -> None:
    _write_pose(ch, "/tof/odometry", c)
    payload = files.payload(c)
    k = c.intrinsics
    # always written: it carries the cloud's organised width × height (K is zero when unknown)
    fx, fy, cx, cy = (float(k.get(n, 0.0)) for n in ("fx", "fy", "cx", "cy"))
    cal = CameraCalibration(frame_id="tof", width=c.width, height=c.height, distortion_model="plumb_bob", D=[0.0] * 5,
                            K=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0], R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                            P=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    cal.timestamp.FromNanoseconds(_ns(c.timestamp))
    ch.write("/tof/calibration", cal, c.timestamp, c.seq)
    if c.encoding == "png16_depth_mm":
        depth = CompressedImage(frame_id="tof", format="png", data=payload)
        depth.timestamp.FromNanoseconds(_ns(c.timestamp))
        ch.write("/tof/depth", depth, c.timestamp, c.seq)
    points = decode_cloud(payload, {"encoding": c.encoding, "width": c.width, "height": c.height, **k})
    ch.write("/tof/points", _xyz_cloud(points, "tof", c.timestamp), c.timestamp, c.seq)


def _write_telemetry(ch: _Channels, sample: TelemetrySample) -> None:
    pose = sample.data.get("pose") if isinstance(sample.data, dict) else None
    if isinstance(pose, dict) and {"x", "y", "yaw"} <= pose.keys():
        tf = FrameTransform(parent_frame_id="world", child_frame_id="base_link")
        tf.timestamp.FromNanoseconds(_ns(sample.timestamp))
        tf.translation.x, tf.translation.y = float(pose["x"]), float(pose["y"])
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = _yaw_quaternion(float(pose["yaw"]))
        ch.write("/tf", tf, sample.timestamp, sample.seq)
    ch.write("/robot/telemetry", {"timestamp": sample.timestamp, **sample.data}, sample.timestamp, sample.seq)


def _write_results(ch: _Channels, db: Session, files: SessionFiles, session_id: str, t: float) -> None:
    from processing.poses import parse_tum
    from server.exports import read_ply_points

    results = files.results_dir(session_id)
    try:
        ch.write("/map/points", _xyz_cloud(read_ply_points(results / "map.ply"), "world", t), t)
    except (OSError, ValueError):
        pass
    try:
        _, poses = parse_tum((results / "trajectory.tum").read_text())
    except (OSError, ValueError):
        poses = np.empty((0, 4, 4))
    if len(poses):
        traj = PosesInFrame(frame_id="world")
        traj.timestamp.FromNanoseconds(_ns(t))
        for T in poses:
            _set_pose(traj.poses.add(), tuple(float(v) for v in T[:3, 3]), _matrix_quaternion(T[:3, :3]))  # type: ignore[arg-type]
        ch.write("/map/trajectory", traj, t)
    defects = list(db.scalars(select(Defect).where(Defect.session_id == session_id).order_by(Defect.id)))
    if defects:
        from server.schemas import DefectPublic

        ch.write("/inspection/defects", {"defects": [DefectPublic.model_validate(d).model_dump(mode="json") for d in defects]}, t)
        placed = [d for d in defects if d.source == "mosaic" and d.world_x_m is not None]
        if placed:
            ch.write("/inspection/defect_markers", _defect_markers(placed, t), t)


def _defect_markers(defects: list[Defect], t: float) -> SceneUpdate:
    """A box and a label per defect on the structure (Foxglove's 3D panel shows them)."""
    update = SceneUpdate()
    for d in defects:
        entity = update.entities.add(frame_id="world", id=f"defect-{d.id}")
        entity.timestamp.FromNanoseconds(_ns(t))
        red, green = (1.0, 0.23) if d.defect_class == "crack" else (1.0, 0.8)
        w, h = max(d.world_w_m or 0.0, 0.005), max(d.world_h_m or 0.0, 0.005)
        cube = entity.cubes.add()
        _set_pose(cube.pose, (d.world_x_m + w / 2, d.world_y_m + h / 2, 0.0), (0.0, 0.0, 0.0, 1.0))
        cube.size.x, cube.size.y, cube.size.z = w, h, 0.004
        cube.color.r, cube.color.g, cube.color.b, cube.color.a = red, green, 0.2, 0.6
        label = entity.texts.add(billboard=True, font_size=14.0, scale_invariant=True,
                                 text=f"#{d.id} {d.defect_class} {d.length_mm or 0:.0f} mm {d.condition_state or ''}".strip())
        _set_pose(label.pose, (d.world_x_m + w / 2, d.world_y_m + h / 2, 0.02), (0.0, 0.0, 0.0, 1.0))
        label.color.r = label.color.g = label.color.b = label.color.a = 1.0
    return update


# --------------------------------------------------------------------------- import


class McapImportError(ValueError):
    """The file is not an MCAP session this station can import."""


def import_session(db: Session, files: SessionFiles, path: Path, *, progress: Progress = lambda f, m: None) -> dict[str, Any]:
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
                db.execute(update(model).where(model.session_id == session_id, model.seq == seq)
                           .values(pose_x=x, pose_y=y, pose_yaw=yaw))
        if not any(counts.values()):
            raise McapImportError("the file holds no camera frames, clouds or telemetry on steelscan's topics")
        db.commit()
    except (McapError, DecodeError, EOFError, KeyError, struct.error) as exc:
        _discard(db, files, session_id)
        raise McapImportError(f"{path.name}: not a readable MCAP session ({type(exc).__name__}: {exc})") from None
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
    note = f"Imported from {name}" + (f" (session {meta['id']})" if meta.get("id") else "")
    return InspectionSession(
        id=session_id, robot_id=None, structure=meta.get("structure") or Path(name).stem, operator=meta.get("operator", ""),
        location=meta.get("location", ""), notes="\n".join(n for n in (meta.get("notes", ""), note) if n),
        status=SessionStatus.ended, started_at=when("started_at") or datetime.now(timezone.utc),
        ended_at=when("ended_at") or datetime.now(timezone.utc), end_reason=meta.get("end_reason") or "imported",
        calibration=calibration if isinstance(calibration, dict) else {},
    )


def _first_pass(fh: BinaryIO) -> tuple[dict[str, str], dict[str, dict[int, tuple[float, float, float]]], dict[int, dict[str, float]], set[int]]:
    """Session metadata, odometry and calibration per sequence number, clouds sent as depth PNG."""
    reader = make_reader(fh)
    meta: dict[str, str] = {}
    for record in reader.iter_metadata():
        if record.name == METADATA:
            meta = dict(record.metadata)
    poses: dict[str, dict[int, tuple[float, float, float]]] = {"/camera/odometry": {}, "/tof/odometry": {}}
    calibration: dict[int, dict[str, float]] = {}
    depth: set[int] = set()
    for _, channel, message in reader.iter_messages(topics=["/camera/odometry", "/tof/odometry", "/tof/calibration", "/tof/depth"],
                                                    log_time_order=False):
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
            poses[channel.topic][message.sequence] = (p.position.x, p.position.y, float(np.arctan2(np.sin(yaw), np.cos(yaw))))
    return meta, poses, calibration, depth


def _second_pass(db: Session, files: SessionFiles, session_id: str, fh: BinaryIO, depth_seqs: set[int],
                 calibration: dict[int, dict[str, float]], progress: Progress) -> dict[str, int]:
    reader = make_reader(fh)
    counts = {"frames": 0, "clouds": 0, "telemetry": 0}
    seen: set[tuple[str, int]] = set()
    for i, (_, channel, m) in enumerate(reader.iter_messages(topics=["/camera/image", "/tof/depth", "/tof/points", "/robot/telemetry"],
                                                             log_time_order=False)):
        topic, seq, t = channel.topic, m.sequence, m.log_time / 1e9
        if topic == "/camera/image":
            img = CompressedImage.FromString(m.data)
            if ("frame", seq) in seen:
                continue
            seen.add(("frame", seq))
            rel = files.frame_relpath(session_id, seq)
            files.write(rel, img.data)
            w, h = _image_size(img.data)
            db.add(Frame(session_id=session_id, seq=seq, timestamp=img.timestamp.ToNanoseconds() / 1e9 or t, width=w, height=h,
                         path=rel, size_bytes=len(img.data)))
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
            db.add(TelemetrySample(session_id=session_id, seq=seq, timestamp=stamp, data=data))
            counts["telemetry"] += 1
        if i % 500 == 499:
            db.flush()
            progress(0.0, f"{i + 1} messages read")
    db.flush()
    return counts


def _cloud_row(files: SessionFiles, session_id: str, seq: int, topic: str, data: bytes, cal: dict[str, float]) -> Cloud:
    intrinsics = {k: cal[k] for k in ("fx", "fy", "cx", "cy") if k in cal}
    if topic == "/tof/depth":
        img = CompressedImage.FromString(data)
        payload, encoding, t = img.data, "png16_depth_mm", img.timestamp.ToNanoseconds() / 1e9
        w, h = _image_size(payload)
        if len(intrinsics) < 4:
            raise McapImportError(f"depth image {seq} has no intrinsics on /tof/calibration")
    else:
        cloud = PointCloud.FromString(data)
        fields = [(f.name, f.offset, f.type) for f in cloud.fields][:3]
        if cloud.point_stride != 12 or fields != [(n, 4 * i, PackedElementField.FLOAT32) for i, n in enumerate("xyz")]:
            raise McapImportError(f"cloud {seq} is not packed float32 x, y, z")
        payload, encoding, t = cloud.data, "xyz_f32", cloud.timestamp.ToNanoseconds() / 1e9
        count = len(payload) // 12
        w, h = int(cal.get("width", 0)), int(cal.get("height", 0))
        if w * h != count:
            w, h = count, 1
    rel = files.cloud_relpath(session_id, seq, encoding)
    files.write(rel, payload)
    return Cloud(session_id=session_id, seq=seq, timestamp=t, encoding=encoding, width=w, height=h, intrinsics=intrinsics,
                 path=rel, size_bytes=len(payload))


def _image_size(data: bytes) -> tuple[int, int]:
    """(width, height) of an encoded image from its header."""
    import io

    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as im:
            return im.size
    except (OSError, UnidentifiedImageError) as exc:
        raise McapImportError(f"an image in the file is not readable ({exc})") from None
