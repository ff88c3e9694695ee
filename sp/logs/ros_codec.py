"""ROS messages <-> sensor frames: the one place that knows both the ROS 2 message layouts and
the frame data model of :mod:`sp.logs.types`.

Encoding (frame -> ROS 2 messages, used by :class:`sp.logs.mcap_log.McapLogWriter`):

=================  =====================================  =====================================
frame              topic(s)                               ROS 2 message type
=================  =====================================  =====================================
LadarScan          ``topic``                              sensor_msgs/msg/PointCloud2: fields
                                                          x y z intensity (float32), t (uint32,
                                                          ns after the stamp), ring (uint16,
                                                          only when the scan has rings)
CameraFrame        ``topic/camera_info``                  sensor_msgs/msg/CameraInfo (plumb_bob)
                   ``topic/depth`` (when depth is set)    sensor_msgs/msg/Image, 32FC1 metres
                   ``topic/image``                        sensor_msgs/msg/Image, mono8 or rgb8
OdometryFrame      ``topic``                              nav_msgs/msg/Odometry
ImuFrame           ``topic``                              sensor_msgs/msg/Imu (no orientation:
                                                          orientation_covariance[0] = -1, REP 145)
TransformFrame     ``topic`` (``/tf_static`` when static) tf2_msgs/msg/TFMessage, one transform
GroundTruthPose    ``topic``                              nav_msgs/msg/Odometry (zero twist)
ObjectBoxes        ``topic``                              vision_msgs/msg/Detection3DArray
                   ``topic/velocities``                   std_msgs/msg/Float64MultiArray
=================  =====================================  =====================================

Detection3D has no velocity field, so box velocities travel on the parallel topic
``<topic>/velocities`` as one std_msgs/msg/Float64MultiArray per Detection3DArray, with the
same log time, rows in the same order as the detections, layout ``[("boxes", M, 3M),
("vxyz", 3, 3)]`` (row-major M x 3, m/s in the boxes' frame). One Detection3D per box:
``bbox.center`` = centre and yaw (rotation about z), ``bbox.size`` = full extents,
``results[0].hypothesis.class_id`` = class name, ``id`` = str(track id).

Decoding (ROS messages -> frames, used by every ROS-based log source) goes through
:class:`FrameAssembler`, which joins the messages of one instant: an image with the depth image
and camera info of its camera, a box array with its velocities.

Stamps: every header stamp is the frame's ``t_ns``; frames read back carry the header stamp
(the sensor's time), while sources yield them in log-time order.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from maps.frames import NS_PER_S, matrix_to_quat, quat_to_matrix, rot_z
from sp.logs.types import (
    CameraFrame,
    Frame,
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    LogError,
    ObjectBoxes,
    OdometryFrame,
    ReadStats,
    TransformFrame,
)

# vision_msgs (ROS 2, 4.x) is not in the rosbags type stores: its definitions, as released.
_VISION_MSGS = {
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
        "vision_msgs/BoundingBox3D bbox\nstring id\n"
    ),
    "vision_msgs/msg/Detection3DArray": (
        "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n"
    ),
}

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
DETECTION3D_ARRAY = "vision_msgs/msg/Detection3DArray"
FLOAT64_MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"

# MCAP channel metadata key saying which frame kind a channel carries (where the message type
# alone is ambiguous: an Odometry can be odometry or ground truth).
KIND_KEY = "frame_kind"

_PF_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_PF_CODES = {"f4": 7, "u4": 6, "u2": 4}
_DEPTH_ENCODINGS = ("32FC1", "16UC1")


class Role(enum.Enum):
    """What a ROS message contributes to the frames (decided before deserialising)."""

    LADAR = "ladar"
    IMAGE = "image"  # colour/intensity or depth image; told apart by its encoding
    CAMERA_INFO = "camera_info"
    ODOMETRY = "odometry"
    GROUND_TRUTH = "ground_truth"
    IMU = "imu"
    TF = "tf"
    BOXES = "boxes"
    BOX_VELOCITIES = "box_velocities"


ROLE_KIND: dict[Role, type] = {
    Role.LADAR: LadarScan,
    Role.IMAGE: CameraFrame,
    Role.CAMERA_INFO: CameraFrame,
    Role.ODOMETRY: OdometryFrame,
    Role.GROUND_TRUTH: GroundTruthPose,
    Role.IMU: ImuFrame,
    Role.TF: TransformFrame,
    Role.BOXES: ObjectBoxes,
    Role.BOX_VELOCITIES: ObjectBoxes,
}


@cache
def typestore() -> Any:
    """The rosbags type store: ROS 2 Humble messages plus vision_msgs."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    for name, text in _VISION_MSGS.items():
        store.register(get_types_from_msg(text, name))
    return store


@cache
def ros2msg_schema(msgtype: str) -> bytes:
    """The ``ros2msg`` schema text of ``msgtype`` (with its dependencies), as rosbag2 writes it."""
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return text.encode()


def role_of(topic: str, msgtype: str, channel_kind: str | None = None) -> Role | None:
    """The role of a message on ``topic``, or None for a message type frames do not carry."""
    ground_truth = channel_kind == "ground_truth_pose" or topic.startswith("/ground_truth")
    if msgtype in (ODOMETRY, "nav_msgs/Odometry"):
        return Role.GROUND_TRUTH if ground_truth else Role.ODOMETRY
    if msgtype in (POSE_STAMPED, "geometry_msgs/PoseStamped") and ground_truth:
        return Role.GROUND_TRUTH
    if msgtype in (FLOAT64_MULTI_ARRAY, "std_msgs/Float64MultiArray"):
        return Role.BOX_VELOCITIES if topic.endswith("/velocities") else None
    return _ROLE_BY_TYPE.get(msgtype.replace("/msg/", "/"))


_ROLE_BY_TYPE = {
    "sensor_msgs/PointCloud2": Role.LADAR,
    "sensor_msgs/Image": Role.IMAGE,
    "sensor_msgs/CameraInfo": Role.CAMERA_INFO,
    "sensor_msgs/Imu": Role.IMU,
    "tf2_msgs/TFMessage": Role.TF,
    "vision_msgs/Detection3DArray": Role.BOXES,
}


def frame_topic(topic: str, role: Role | None) -> str:
    """The topic of the frame a message feeds: a camera's parts share their parent topic."""
    if role in (Role.IMAGE, Role.CAMERA_INFO):
        return topic.rsplit("/", 1)[0] or "/"
    if role is Role.BOX_VELOCITIES:
        return topic.removesuffix("/velocities")
    return topic


# --------------------------------------------------------------------------- encoding


Buffer = bytes | memoryview


@dataclass(frozen=True, slots=True)
class Encoded:
    """One ROS 2 message: topic, type, MCAP channel kind, and its little-endian CDR bytes as
    parts (bulk arrays are referenced, not copied: a frame's image is one of the parts)."""

    topic: str
    msgtype: str
    kind: str
    parts: tuple[Buffer, ...]

    @property
    def nbytes(self) -> int:
        return sum(len(p) for p in self.parts)


def serialize(enc: Encoded) -> bytes:
    """The CDR bytes of an encoded message, joined (the writer uses ``enc.parts`` as is)."""
    return b"".join(enc.parts)


def _cdr(message: Any, msgtype: str) -> tuple[Buffer]:
    return (typestore().serialize_cdr(message, msgtype, little_endian=True),)


def _as_bytes(a: np.ndarray) -> memoryview:
    return memoryview(np.ascontiguousarray(a)).cast("B")


def _cdr_around_bulk(
    message: Any, msgtype: str, bulk: memoryview, after: int
) -> tuple[Buffer, ...]:
    """CDR parts of ``message`` whose uint8[] field (left empty in ``message``) holds ``bulk``.

    ``after`` is how many CDR bytes follow that field. The small rest is serialised once and
    the bulk goes between its two halves untouched, so it is never copied.
    """
    small = typestore().serialize_cdr(message, msgtype, little_endian=True)
    cut = len(small) - after - 4  # the empty sequence's uint32 length
    head = bytes(small[:cut]) + struct.pack("<I", len(bulk))
    return (head, bulk, bytes(small[len(small) - after :])) if after else (head, bulk)


def encode_frame(frame: Frame) -> list[Encoded]:
    """The ROS 2 messages that carry ``frame`` (see the module table). Raises LogError."""
    encoder = _ENCODERS.get(type(frame))
    if encoder is None:
        raise LogError(f"cannot write a {type(frame).__name__}: not a sensor frame type")
    return encoder(frame)


def _t(name: str) -> Any:
    return typestore().types[name]


def _header(t_ns: int, frame_id: str) -> Any:
    sec, nanosec = divmod(int(t_ns), NS_PER_S)
    if not -(2**31) <= sec < 2**31:
        raise LogError(f"t_ns = {t_ns} does not fit a ROS time (int32 seconds)")
    stamp = _t("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)
    return _t("std_msgs/msg/Header")(stamp=stamp, frame_id=frame_id)


def _pose(T: np.ndarray) -> Any:
    T = np.asarray(T, dtype=np.float64)
    x, y, z = (float(v) for v in T[:3, 3])
    qx, qy, qz, qw = (float(v) for v in matrix_to_quat(T[:3, :3]))
    return _t("geometry_msgs/msg/Pose")(
        position=_t("geometry_msgs/msg/Point")(x=x, y=y, z=z),
        orientation=_t("geometry_msgs/msg/Quaternion")(x=qx, y=qy, z=qz, w=qw),
    )


def _vector3(v: np.ndarray) -> Any:
    x, y, z = (float(c) for c in np.asarray(v, dtype=np.float64).reshape(3))
    return _t("geometry_msgs/msg/Vector3")(x=x, y=y, z=z)


def _f64(a: np.ndarray, n: int) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(n))


def _encode_ladar(scan: LadarScan) -> list[Encoded]:
    n = scan.n_points
    t_off = np.asarray(scan.t_offset_ns, dtype=np.int64)
    if n and (t_off.min() < 0 or t_off.max() >= 2**32):
        raise LogError(
            f"LadarScan on {scan.topic} at t_ns={scan.t_ns}: t_offset_ns spans "
            f"[{t_off.min()}, {t_off.max()}], outside the uint32 't' field"
        )
    names = ["x", "y", "z", "intensity", "t"]
    formats = ["<f4", "<f4", "<f4", "<f4", "<u4"]
    if scan.ring is not None:
        names.append("ring")
        formats.append("<u2")
    dtype = np.dtype({"names": names, "formats": formats})  # packed: offsets follow sizes
    field = _t("sensor_msgs/msg/PointField")
    fields = [
        field(name=k, offset=dtype.fields[k][1], datatype=_PF_CODES[dtype[k].str[1:]], count=1)
        for k in names
    ]
    msg = _t(POINTCLOUD2)(
        header=_header(scan.t_ns, scan.frame_id),
        height=1,
        width=n,
        fields=fields,
        is_bigendian=False,
        point_step=dtype.itemsize,
        row_step=dtype.itemsize * n,
        data=np.zeros(0, np.uint8),
        is_dense=True,
    )
    cloud = np.empty(n, dtype=dtype)
    xyz = np.asarray(scan.points_xyz, dtype=np.float32).reshape(n, 3)
    cloud["x"], cloud["y"], cloud["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    cloud["intensity"] = scan.intensity
    cloud["t"] = t_off
    if scan.ring is not None:
        cloud["ring"] = scan.ring
    parts = _cdr_around_bulk(msg, POINTCLOUD2, _as_bytes(cloud.view(np.uint8)), after=1)
    return [Encoded(scan.topic, POINTCLOUD2, "ladar_scan", parts)]


def _image(t_ns: int, frame_id: str, pixels: np.ndarray, encoding: str) -> tuple[Buffer, ...]:
    """CDR parts of an Image message of ``pixels`` (referenced, not copied)."""
    h, w = pixels.shape[:2]
    msg = _t(IMAGE)(
        header=_header(t_ns, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=pixels.nbytes // max(h, 1),
        data=np.zeros(0, np.uint8),
    )
    return _cdr_around_bulk(msg, IMAGE, _as_bytes(pixels), after=0)


def _encode_camera(cam: CameraFrame) -> list[Encoded]:
    image = np.asarray(cam.image)
    if image.dtype != np.uint8 or not (
        image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)
    ):
        raise LogError(
            f"CameraFrame on {cam.topic} at t_ns={cam.t_ns}: image {image.dtype} "
            f"{image.shape} is neither (H, W) nor (H, W, 3) uint8"
        )
    h, w = image.shape[:2]
    K = _f64(cam.K, 9)
    P = np.zeros((3, 4))
    P[:, :3] = K.reshape(3, 3)
    info = _t(CAMERA_INFO)(
        header=_header(cam.t_ns, cam.frame_id),
        height=h,
        width=w,
        distortion_model="plumb_bob",
        d=_f64(cam.dist, 5),
        k=K,
        r=np.eye(3).reshape(9),
        p=P.reshape(12),
        binning_x=0,
        binning_y=0,
        roi=_t("sensor_msgs/msg/RegionOfInterest")(
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )
    out = [Encoded(f"{cam.topic}/camera_info", CAMERA_INFO, "camera_info", _cdr(info, CAMERA_INFO))]
    if cam.depth is not None:
        depth = _image(cam.t_ns, cam.frame_id, np.asarray(cam.depth, dtype="<f4"), "32FC1")
        out.append(Encoded(f"{cam.topic}/depth", IMAGE, "camera_depth", depth))
    encoding = "mono8" if image.ndim == 2 else "rgb8"
    pixels = _image(cam.t_ns, cam.frame_id, image, encoding)
    out.append(Encoded(f"{cam.topic}/image", IMAGE, "camera_image", pixels))
    return out


def _cdr_string(text: str, pos: int) -> tuple[bytes, int]:
    """A CDR string at byte ``pos`` (4-aligned): uint32 length with NUL, bytes, NUL."""
    raw = text.encode() + b"\0"
    pad = -pos % 4
    return b"\0" * pad + struct.pack("<I", len(raw)) + raw, pos + pad + 4 + len(raw)


def _odometry_cdr(
    t_ns: int,
    frame_id: str,
    child: str,
    T: np.ndarray,
    lin: np.ndarray,
    ang: np.ndarray,
    pose_cov: np.ndarray,
    twist_cov: np.ndarray,
) -> tuple[Buffer]:
    """nav_msgs/msg/Odometry packed directly (it is written at high rate): header, child
    frame, then 85 float64 (position, orientation xyzw, 36 covariance, linear, angular, 36
    covariance) 8-aligned. The tests check it byte for byte against rosbags' serialiser."""
    sec, nanosec = divmod(int(t_ns), NS_PER_S)
    if not -(2**31) <= sec < 2**31:
        raise LogError(f"t_ns = {t_ns} does not fit a ROS time (int32 seconds)")
    frame, pos = _cdr_string(frame_id, 8)
    child_part, pos = _cdr_string(child, pos)
    T = np.asarray(T, dtype=np.float64)
    doubles = np.concatenate(
        [
            T[:3, 3],
            matrix_to_quat(T[:3, :3]),
            _f64(pose_cov, 36),
            _f64(lin, 3),
            _f64(ang, 3),
            _f64(twist_cov, 36),
        ]
    ).astype("<f8")
    cdr = b"\0\1\0\0" + struct.pack("<iI", sec, nanosec) + frame + child_part
    return (cdr + b"\0" * (-pos % 8) + doubles.tobytes(),)


def _encode_odometry(o: OdometryFrame) -> list[Encoded]:
    parts = _odometry_cdr(
        o.t_ns,
        o.frame_id,
        o.child_frame_id,
        o.T_parent_child,
        o.twist_linear,
        o.twist_angular,
        o.pose_covariance,
        o.twist_covariance,
    )
    return [Encoded(o.topic, ODOMETRY, "odometry", parts)]


def _encode_ground_truth(g: GroundTruthPose) -> list[Encoded]:
    z3, z66 = np.zeros(3), np.zeros((6, 6))
    parts = _odometry_cdr(g.t_ns, g.frame_id, g.child_frame_id, g.T_parent_child, z3, z3, z66, z66)
    return [Encoded(g.topic, ODOMETRY, "ground_truth_pose", parts)]


def _encode_imu(m: ImuFrame) -> list[Encoded]:
    q = _t("geometry_msgs/msg/Quaternion")
    orientation_cov = np.zeros(9)
    if m.orientation_xyzw is None:
        orientation, orientation_cov[0] = q(x=0.0, y=0.0, z=0.0, w=1.0), -1.0
    else:
        x, y, z, w = (float(v) for v in np.asarray(m.orientation_xyzw, dtype=np.float64))
        orientation = q(x=x, y=y, z=z, w=w)
    msg = _t(IMU)(
        header=_header(m.t_ns, m.frame_id),
        orientation=orientation,
        orientation_covariance=orientation_cov,
        angular_velocity=_vector3(m.angular_velocity),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=_vector3(m.linear_acceleration),
        linear_acceleration_covariance=np.zeros(9),
    )
    return [Encoded(m.topic, IMU, "imu", _cdr(msg, IMU))]


def _encode_transform(tf: TransformFrame) -> list[Encoded]:
    pose = _pose(tf.T_parent_child)
    p = pose.position
    stamped = _t("geometry_msgs/msg/TransformStamped")(
        header=_header(tf.t_ns, tf.parent_frame_id),
        child_frame_id=tf.child_frame_id,
        transform=_t("geometry_msgs/msg/Transform")(
            translation=_vector3(np.array([p.x, p.y, p.z])), rotation=pose.orientation
        ),
    )
    topic = "/tf_static" if tf.static and tf.topic == "/tf" else tf.topic
    msg = _t(TF_MESSAGE)(transforms=[stamped])
    return [Encoded(topic, TF_MESSAGE, "transform", _cdr(msg, TF_MESSAGE))]


def _encode_boxes(b: ObjectBoxes) -> list[Encoded]:
    m = len(b)
    header = _header(b.t_ns, b.frame_id)
    hyp = _t("vision_msgs/msg/ObjectHypothesis")
    hyp_pose = _t("vision_msgs/msg/ObjectHypothesisWithPose")
    pwc = _t("geometry_msgs/msg/PoseWithCovariance")
    centers = np.asarray(b.centers, dtype=np.float64).reshape(m, 3)
    sizes = np.asarray(b.sizes, dtype=np.float64).reshape(m, 3)
    detections = []
    for i in range(m):
        T = np.eye(4)
        T[:3, :3] = rot_z(float(b.yaws[i]))
        T[:3, 3] = centers[i]
        center = _pose(T)
        detections.append(
            _t("vision_msgs/msg/Detection3D")(
                header=header,
                results=[
                    hyp_pose(
                        hypothesis=hyp(class_id=str(b.classes[i]), score=1.0),
                        pose=pwc(pose=center, covariance=np.zeros(36)),
                    )
                ],
                bbox=_t("vision_msgs/msg/BoundingBox3D")(center=center, size=_vector3(sizes[i])),
                id=str(int(b.ids[i])),
            )
        )
    boxes = _t(DETECTION3D_ARRAY)(header=header, detections=detections)
    dim = _t("std_msgs/msg/MultiArrayDimension")
    velocities = _t(FLOAT64_MULTI_ARRAY)(
        layout=_t("std_msgs/msg/MultiArrayLayout")(
            dim=[dim(label="boxes", size=m, stride=3 * m), dim(label="vxyz", size=3, stride=3)],
            data_offset=0,
        ),
        data=_f64(b.velocities, 3 * m),
    )
    return [
        Encoded(
            f"{b.topic}/velocities",
            FLOAT64_MULTI_ARRAY,
            "box_velocities",
            _cdr(velocities, FLOAT64_MULTI_ARRAY),
        ),
        Encoded(b.topic, DETECTION3D_ARRAY, "object_boxes", _cdr(boxes, DETECTION3D_ARRAY)),
    ]


_ENCODERS = {
    LadarScan: _encode_ladar,
    CameraFrame: _encode_camera,
    OdometryFrame: _encode_odometry,
    ImuFrame: _encode_imu,
    TransformFrame: _encode_transform,
    GroundTruthPose: _encode_ground_truth,
    ObjectBoxes: _encode_boxes,
}


# --------------------------------------------------------------------------- decoding


def stamp_ns(header: Any) -> int:
    """int64 nanoseconds of a ROS header stamp."""
    return int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec)


def _T_of(position: Any, orientation: Any) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(
        np.array([orientation.x, orientation.y, orientation.z, orientation.w])
    )
    T[:3, 3] = position.x, position.y, position.z
    return T


def _xyz(v: Any) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=np.float64)


def decode_pointcloud2(msg: Any, topic: str, stats: ReadStats) -> LadarScan:
    """PointCloud2 -> LadarScan. Non-finite points are dropped and counted in ``stats``.

    Per-point time from a field ``t`` or ``offset_time`` (integer ns after the stamp) or
    ``time`` (float seconds after the stamp); ring from ``ring`` (or ``laser_number``).
    """
    order = ">" if msg.is_bigendian else "<"
    fields = {f.name: f for f in msg.fields}
    if not {"x", "y", "z"} <= fields.keys():
        raise ValueError(f"PointCloud2 without x, y, z fields (has {sorted(fields)})")
    dtype = np.dtype(
        {
            "names": list(fields),
            "formats": [order + _PF_DTYPES[f.datatype] for f in fields.values()],
            "offsets": [f.offset for f in fields.values()],
            "itemsize": msg.point_step,
        }
    )
    rows = np.frombuffer(np.asarray(msg.data, dtype=np.uint8), dtype=np.uint8)
    rows = rows[: msg.height * msg.row_step].reshape(msg.height, msg.row_step)
    cloud = rows[:, : msg.width * msg.point_step].copy().view(dtype).reshape(-1)
    xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float32)
    finite = np.isfinite(xyz).all(axis=1)
    n_bad = int(finite.size - finite.sum())
    if n_bad:
        stats.dropped_nonfinite_points += n_bad
        cloud, xyz = cloud[finite], xyz[finite]
    n = xyz.shape[0]
    intensity = (
        cloud["intensity"].astype(np.float32) if "intensity" in fields else np.zeros(n, np.float32)
    )
    if "t" in fields or "offset_time" in fields:
        t_off = cloud["t" if "t" in fields else "offset_time"].astype(np.int64)
    elif "time" in fields:
        t_off = np.round(cloud["time"].astype(np.float64) * NS_PER_S).astype(np.int64)
    else:
        t_off = np.zeros(n, np.int64)
    ring_name = "ring" if "ring" in fields else "laser_number" if "laser_number" in fields else None
    ring = cloud[ring_name].astype(np.uint16) if ring_name else None
    return LadarScan(
        t_ns=stamp_ns(msg.header),
        frame_id=msg.header.frame_id,
        points_xyz=xyz,
        intensity=intensity,
        t_offset_ns=t_off,
        ring=ring,
        topic=topic,
    )


def _image_pixels(msg: Any) -> np.ndarray:
    """Image message -> (H, W) uint8, (H, W, 3) uint8 RGB, or (H, W) float32 depth in metres."""
    enc = msg.encoding
    channels, dtype = {
        "mono8": (1, "u1"),
        "8UC1": (1, "u1"),
        "rgb8": (3, "u1"),
        "8UC3": (3, "u1"),
        "bgr8": (3, "u1"),
        "rgba8": (4, "u1"),
        "bgra8": (4, "u1"),
        "32FC1": (1, "f4"),
        "16UC1": (1, "u2"),
        "mono16": (1, "u2"),
    }.get(enc, (0, ""))
    if not channels:
        raise ValueError(f"image encoding {enc!r} is not supported")
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    raw = np.asarray(msg.data, dtype=np.uint8).reshape(msg.height, msg.step)
    row_bytes = msg.width * channels * dt.itemsize
    px = raw[:, :row_bytes].copy().view(dt).reshape(msg.height, msg.width, channels)
    if enc.startswith("bgr"):
        px = px[..., 2::-1]
    px = px[..., :3] if channels == 4 else px
    px = px[..., 0] if channels == 1 else px
    if enc == "32FC1":
        return px.astype(np.float32)
    if dt.itemsize == 2:  # 16-bit depth in millimetres, 0 = unknown
        depth = px.astype(np.float32) / 1000.0
        depth[px == 0] = np.nan
        return depth
    return np.ascontiguousarray(px)


def decode_odometry(msg: Any, topic: str) -> OdometryFrame:
    """nav_msgs/Odometry -> OdometryFrame."""
    return OdometryFrame(
        t_ns=stamp_ns(msg.header),
        frame_id=msg.header.frame_id,
        child_frame_id=msg.child_frame_id,
        T_parent_child=_T_of(msg.pose.pose.position, msg.pose.pose.orientation),
        twist_linear=_xyz(msg.twist.twist.linear),
        twist_angular=_xyz(msg.twist.twist.angular),
        pose_covariance=np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6).copy(),
        twist_covariance=np.asarray(msg.twist.covariance, dtype=np.float64).reshape(6, 6).copy(),
        topic=topic,
    )


def decode_ground_truth(msg: Any, topic: str) -> GroundTruthPose:
    """nav_msgs/Odometry (or geometry_msgs/PoseStamped, child "base_link") -> GroundTruthPose."""
    pose = msg.pose.pose if hasattr(msg, "child_frame_id") else msg.pose
    return GroundTruthPose(
        t_ns=stamp_ns(msg.header),
        frame_id=msg.header.frame_id,
        child_frame_id=getattr(msg, "child_frame_id", "base_link"),
        T_parent_child=_T_of(pose.position, pose.orientation),
        topic=topic,
    )


def decode_imu(msg: Any, topic: str) -> ImuFrame:
    """sensor_msgs/Imu -> ImuFrame (orientation None when orientation_covariance[0] == -1)."""
    o = msg.orientation
    has_orientation = float(msg.orientation_covariance[0]) != -1.0
    return ImuFrame(
        t_ns=stamp_ns(msg.header),
        frame_id=msg.header.frame_id,
        angular_velocity=_xyz(msg.angular_velocity),
        linear_acceleration=_xyz(msg.linear_acceleration),
        orientation_xyzw=np.array([o.x, o.y, o.z, o.w]) if has_orientation else None,
        topic=topic,
    )


def decode_tf(msg: Any, topic: str) -> list[TransformFrame]:
    """tf2_msgs/TFMessage -> one TransformFrame per transform (static on ``*tf_static``)."""
    static = topic.endswith("tf_static")
    return [
        TransformFrame(
            t_ns=stamp_ns(ts.header),
            parent_frame_id=ts.header.frame_id,
            child_frame_id=ts.child_frame_id,
            T_parent_child=_T_of(ts.transform.translation, ts.transform.rotation),
            static=static,
            topic=topic,
        )
        for ts in msg.transforms
    ]


class FrameAssembler:
    """Turns deserialised ROS messages, fed in log-time order, into frames.

    Messages with the same log time form one instant; within it, camera infos, depth images and
    box velocities are taken first so that the image / box array they belong to finds them.
    A camera's intrinsics are the latest CameraInfo on its topic (NaN before the first one).
    Track ids that are not integers get stable integer ids in order of first appearance.
    """

    def __init__(
        self,
        stats: ReadStats,
        kinds: tuple[type, ...] | None = None,
        on_error: Callable[[str], None] | None = None,
    ) -> None:
        self.stats = stats
        self.kinds = kinds
        self.on_error = on_error
        self._pending: list[tuple[str, Role, Any]] = []
        self._pending_t: int | None = None
        self._camera_info: dict[str, Any] = {}
        self._depth: dict[str, tuple[int, np.ndarray]] = {}
        self._velocities: dict[str, np.ndarray] = {}
        self._track_ids: dict[str, int] = {}

    def wants(self, role: Role | None) -> bool:
        """Whether messages of ``role`` are worth deserialising for the requested kinds."""
        if role is None:
            return False
        return self.kinds is None or ROLE_KIND[role] in self.kinds

    def push(self, topic: str, role: Role, message: Any, log_t_ns: int) -> list[Frame]:
        """Add one message; returns the frames completed by the instant before it."""
        out: list[Frame] = []
        if self._pending_t is not None and log_t_ns != self._pending_t:
            out = self.flush()
        self._pending_t = log_t_ns
        self._pending.append((topic, role, message))
        return out

    def flush(self) -> list[Frame]:
        """Decode the messages of the pending instant."""
        batch = sorted(self._pending, key=lambda p: not _is_prerequisite(*p))
        self._pending, self._pending_t = [], None
        out: list[Frame] = []
        for topic, role, message in batch:
            try:
                out.extend(self._decode(topic, role, message))
            except (ValueError, KeyError, IndexError, AttributeError) as exc:
                problem = f"{topic}: cannot make a frame of a {role.value} message: {exc}"
                if self.on_error is None:
                    raise LogError(problem) from exc
                self.on_error(problem)
        return out

    def _decode(self, topic: str, role: Role, msg: Any) -> Iterable[Frame]:
        if role is Role.LADAR:
            return [decode_pointcloud2(msg, topic, self.stats)]
        if role is Role.ODOMETRY:
            return [decode_odometry(msg, topic)]
        if role is Role.GROUND_TRUTH:
            return [decode_ground_truth(msg, topic)]
        if role is Role.IMU:
            return [decode_imu(msg, topic)]
        if role is Role.TF:
            return decode_tf(msg, topic)
        if role is Role.CAMERA_INFO:
            self._camera_info[frame_topic(topic, role)] = msg
            return []
        if role is Role.BOX_VELOCITIES:
            data = np.asarray(msg.data, dtype=np.float64)
            self._velocities[frame_topic(topic, role)] = data.reshape(-1, 3).copy()
            return []
        if role is Role.BOXES:
            return [self._boxes(msg, topic)]
        return self._image(msg, topic)

    def _image(self, msg: Any, topic: str) -> list[Frame]:
        base = frame_topic(topic, Role.IMAGE)
        t_ns = stamp_ns(msg.header)
        pixels = _image_pixels(msg)
        if _is_depth(topic, msg):
            self._depth[base] = (t_ns, pixels)
            return []
        depth = self._depth.pop(base, None)
        info = self._camera_info.get(base)
        if info is None:
            self.stats.note(f"{topic}: no CameraInfo before the image at t_ns={t_ns}; K is NaN")
            K, dist = np.full((3, 3), np.nan), np.zeros(5)
        else:
            K = np.asarray(info.k, dtype=np.float64).reshape(3, 3).copy()
            dist = np.zeros(5)
            d = np.asarray(info.d, dtype=np.float64)[:5]
            dist[: d.size] = d
        return [
            CameraFrame(
                t_ns=t_ns,
                frame_id=msg.header.frame_id,
                image=pixels,
                K=K,
                depth=depth[1] if depth is not None and depth[0] == t_ns else None,
                dist=dist,
                topic=base,
            )
        ]

    def _track_id(self, text: str) -> int:
        try:
            return int(text)
        except ValueError:
            return self._track_ids.setdefault(text, len(self._track_ids))

    def _boxes(self, msg: Any, topic: str) -> ObjectBoxes:
        dets = msg.detections
        m = len(dets)
        quats = np.array(
            [[d.bbox.center.orientation.__getattribute__(c) for c in "xyzw"] for d in dets]
        ).reshape(m, 4)
        x, y, z, w = quats.T
        velocities = self._velocities.pop(topic, None)
        if velocities is None or velocities.shape[0] != m:
            velocities = np.full((m, 3), np.nan)
        return ObjectBoxes(
            t_ns=stamp_ns(msg.header),
            frame_id=msg.header.frame_id,
            ids=np.array([self._track_id(d.id) for d in dets], dtype=np.int64),
            classes=[d.results[0].hypothesis.class_id if d.results else "" for d in dets],
            centers=np.array([_xyz(d.bbox.center.position) for d in dets]).reshape(m, 3),
            sizes=np.array([_xyz(d.bbox.size) for d in dets]).reshape(m, 3),
            yaws=np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)),
            velocities=velocities,
            topic=topic,
        )


def _is_depth(topic: str, msg: Any) -> bool:
    return msg.encoding in _DEPTH_ENCODINGS or "depth" in topic.rsplit("/", 1)[-1]


def _is_prerequisite(topic: str, role: Role, msg: Any) -> bool:
    """Messages an instant's image or box array needs before it: infos, depth, velocities."""
    if role is Role.IMAGE:
        return _is_depth(topic, msg)
    return role in (Role.CAMERA_INFO, Role.BOX_VELOCITIES)
