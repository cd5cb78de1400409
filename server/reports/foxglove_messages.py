"""The Foxglove messages of a robot's data, built from a message's own fields: what the
MCAP export (:mod:`server.reports.mcap_export`) writes of each stored frame, cloud and
telemetry sample, and what the live Foxglove server (:mod:`server.live.foxglove`) sends of
each robot message as it arrives. Each builder returns ``(topic, message)`` records in the
order they are written; a message is a ``foxglove_schemas_protobuf`` one, or a dict sent
as JSON."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from mcap_protobuf.schema import build_file_descriptor_set

from robot_link.clouds import decode_cloud

Record = tuple[str, Any]  # (topic, protobuf message or JSON dict)
Pose = tuple[float, float, float]  # the robot on the surface: x, y (m), yaw (rad)

# the topics of a robot's own messages and their schemas (None: JSON); the export adds
# the session's results, written once, and the live server the preview video
TOPICS: dict[str, type | None] = {
    "/camera/image": CompressedImage,
    "/camera/odometry": PoseInFrame,
    "/tof/points": PointCloud,
    "/tof/depth": CompressedImage,
    "/tof/calibration": CameraCalibration,
    "/tof/odometry": PoseInFrame,
    "/tf": FrameTransform,
    "/robot/telemetry": None,
}
CLOUD_TOPICS = ("/tof/odometry", "/tof/calibration", "/tof/depth", "/tof/points")


def ns(t: float) -> int:
    """Seconds since the epoch as whole nanoseconds (never negative)."""
    return max(0, int(round(t * 1e9)))


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """The rotation by ``yaw`` about z as a quaternion (x, y, z, w)."""
    return 0.0, 0.0, float(np.sin(yaw / 2)), float(np.cos(yaw / 2))


def matrix_quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """A rotation matrix as a quaternion (x, y, z, w)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return float(x), float(y), float(z), float(w)


def set_pose(
    pose: Any, xyz: tuple[float, float, float], q: tuple[float, float, float, float]
) -> None:
    """Fill a ``foxglove.Pose`` from a position and a quaternion."""
    pose.position.x, pose.position.y, pose.position.z = xyz
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = q


def schema_bytes(message_class: type) -> bytes:
    """A protobuf message's schema as Foxglove reads it: its serialised FileDescriptorSet."""
    return bytes(build_file_descriptor_set(message_class).SerializeToString())


def pose_of(meta: Mapping[str, Any]) -> Pose | None:
    """The pose a robot message's meta carries, if any."""
    pose = meta.get("pose")
    if isinstance(pose, Mapping) and {"x", "y", "yaw"} <= pose.keys():
        return float(pose["x"]), float(pose["y"]), float(pose["yaw"])
    return None


def xyz_cloud(points: np.ndarray, frame_id: str, t: float) -> PointCloud:
    """Points (N×3 or W×H×3, metres) as a ``foxglove.PointCloud`` of float32 x, y, z."""
    msg = PointCloud(
        frame_id=frame_id, point_stride=12, data=np.ascontiguousarray(points, dtype="<f4").tobytes()
    )
    msg.timestamp.FromNanoseconds(ns(t))
    msg.pose.orientation.w = 1.0
    for i, name in enumerate("xyz"):
        msg.fields.add(name=name, offset=4 * i, type=PackedElementField.FLOAT32)
    return msg


def pose_in_frame(pose: Pose, t: float) -> PoseInFrame:
    """The robot's pose in the world frame."""
    msg = PoseInFrame(frame_id="world")
    msg.timestamp.FromNanoseconds(ns(t))
    set_pose(msg.pose, (pose[0], pose[1], 0.0), yaw_quaternion(pose[2]))
    return msg


def compressed_image(data: bytes, frame_id: str, fmt: str, t: float) -> CompressedImage:
    """An image's bytes as received (``fmt``: jpeg, png)."""
    msg = CompressedImage(frame_id=frame_id, format=fmt, data=data)
    msg.timestamp.FromNanoseconds(ns(t))
    return msg


def frame_records(jpeg: bytes, pose: Pose | None, t: float) -> list[Record]:
    """A camera frame: the robot's pose when it was taken, then the image."""
    records: list[Record] = []
    if pose is not None:
        records.append(("/camera/odometry", pose_in_frame(pose, t)))
    records.append(("/camera/image", compressed_image(jpeg, "camera", "jpeg", t)))
    return records


def cloud_records(
    payload: bytes,
    encoding: str,
    width: int,
    height: int,
    intrinsics: Mapping[str, Any],
    pose: Pose | None,
    t: float,
) -> tuple[list[Record], bool]:
    """A ToF cloud: the robot's pose, the ToF calibration (always: it carries the cloud's
    organised width × height; K is zero when unknown), the depth PNG as received and the
    points; False when the payload cannot be read as a cloud (no points then)."""
    records: list[Record] = []
    if pose is not None:
        records.append(("/tof/odometry", pose_in_frame(pose, t)))
    fx, fy, cx, cy = (float(intrinsics.get(n) or 0.0) for n in ("fx", "fy", "cx", "cy"))
    cal = CameraCalibration(
        frame_id="tof",
        width=width,
        height=height,
        distortion_model="plumb_bob",
        D=[0.0] * 5,
        K=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    )
    cal.timestamp.FromNanoseconds(ns(t))
    records.append(("/tof/calibration", cal))
    if encoding == "png16_depth_mm":
        records.append(("/tof/depth", compressed_image(payload, "tof", "png", t)))
    known = {k: v for k, v in intrinsics.items() if k in ("fx", "fy", "cx", "cy") and v is not None}
    try:
        points = decode_cloud(
            payload, {"encoding": encoding, "width": width, "height": height, **known}
        )
    except ValueError:  # stored as received, but not a readable cloud: no points for it
        return records, False
    records.append(("/tof/points", xyz_cloud(points, "tof", t)))
    return records, True


def telemetry_records(data: Mapping[str, Any], t: float) -> list[Record]:
    """A telemetry sample: the robot's transform in the world (world → base_link) when it
    carries a pose, then the sample as JSON."""
    records: list[Record] = []
    pose = pose_of(data)
    if pose is not None:
        tf = FrameTransform(parent_frame_id="world", child_frame_id="base_link")
        tf.timestamp.FromNanoseconds(ns(t))
        tf.translation.x, tf.translation.y = pose[0], pose[1]
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = yaw_quaternion(pose[2])
        records.append(("/tf", tf))
    records.append(("/robot/telemetry", {"timestamp": t, **data}))
    return records


def mount_records(calibration: Mapping[str, Any], t: float) -> list[Record]:
    """Where the camera and the ToF sensor sit on the robot (base_link → camera, tof), from
    the session's calibration."""
    records: list[Record] = []
    cam = (calibration.get("camera") or {}).get("T_robot_camera")
    if cam is not None:
        tf = FrameTransform(parent_frame_id="base_link", child_frame_id="camera")
        tf.timestamp.FromNanoseconds(ns(t))
        tf.translation.x, tf.translation.y = float(cam[0]), float(cam[1])
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = yaw_quaternion(float(cam[2]))
        records.append(("/tf", tf))
    tof = (calibration.get("tof") or {}).get("T_robot_tof")
    if tof is not None:
        T = np.asarray(tof, dtype=np.float64)
        tf = FrameTransform(parent_frame_id="base_link", child_frame_id="tof")
        tf.timestamp.FromNanoseconds(ns(t))
        tf.translation.x, tf.translation.y, tf.translation.z = (float(v) for v in T[:3, 3])
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = matrix_quaternion(T[:3, :3])
        records.append(("/tf", tf))
    return records
