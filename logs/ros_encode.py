"""Sensor frames -> ROS 2 messages (CDR bytes), for :class:`logs.mcap_log.McapLogWriter`.

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
("vxyz", 3, 3)]`` (row-major M x 3, m/s in the boxes' frame); when the boxes carry
``n_returns``, a fourth column holds it: ``[("boxes", M, 4M), ("vxyz_returns", 4, 4)]``.
One Detection3D per box: ``bbox.center`` = centre and yaw (rotation about z), ``bbox.size`` =
full extents, ``results[0].hypothesis.class_id`` = class name, ``id`` = str(track id).

Every header stamp is the frame's ``t_ns``. Read back, arrays and times come back exactly;
poses pass through quaternions (equal to ~1e-15) and yaws come back wrapped to (-pi, pi].
Bulk arrays (point clouds, images) are never serialised through Python objects: the small
rest of the message is, and the array bytes go between its halves (see ``_cdr_around_bulk``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.geometry import NS_PER_S, matrix_to_quat, rot_z
from logs.ros_types import (
    CAMERA_INFO,
    DETECTION3D_ARRAY,
    FLOAT64_MULTI_ARRAY,
    IMAGE,
    IMU,
    ODOMETRY,
    POINTCLOUD2,
    TF_MESSAGE,
    typestore,
)
from logs.types import (
    CameraFrame,
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    LogError,
    LogMessage,
    ObjectBoxes,
    OdometryFrame,
    TransformFrame,
)

_PF_CODES = {"f4": 7, "u4": 6, "u2": 4}  # sensor_msgs/PointField datatypes

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


def encode_frame(frame: LogMessage) -> list[Encoded]:
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
    rows = np.asarray(b.velocities, dtype=np.float64).reshape(m, 3)
    label = "vxyz"
    if b.n_returns is not None:
        returns = np.asarray(b.n_returns, dtype=np.float64).reshape(m, 1)
        rows, label = np.hstack([rows, returns]), "vxyz_returns"
    n = rows.shape[1]
    velocities = _t(FLOAT64_MULTI_ARRAY)(
        layout=_t("std_msgs/msg/MultiArrayLayout")(
            dim=[dim(label="boxes", size=m, stride=n * m), dim(label=label, size=n, stride=n)],
            data_offset=0,
        ),
        data=_f64(rows, n * m),
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
