"""ROS messages -> sensor frames, for every ROS-based log source (MCAP files, ROS bags).

:class:`FrameAssembler` joins the messages of one instant: an image with the depth image and
camera info of its camera, a box array with its velocities (the topics and layouts are those of
:mod:`logs.ros_encode`). Frames carry their header stamp (the sensor's time) as ``t_ns``,
while sources yield them in log-time order. ROS 1 messages decoded by rosbags have the same
field names, so the same code reads them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from core.geometry import NS_PER_S, quat_to_matrix
from logs.ros_types import ROLE_KIND, Role, frame_topic
from logs.types import (
    CameraFrame,
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    LogError,
    LogMessage,
    ObjectBoxes,
    OdometryFrame,
    ReadStats,
    TransformFrame,
)

_PF_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_DEPTH_ENCODINGS = ("32FC1", "16UC1")


def stamp_ns(header: Any) -> int:
    """int64 nanoseconds of a ROS header stamp."""
    return int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec)


def _T_of(position: Any, orientation: Any) -> np.ndarray:
    """4x4 pose of a ROS position and orientation quaternion."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(
        np.array([orientation.x, orientation.y, orientation.z, orientation.w])
    )
    T[:3, 3] = position.x, position.y, position.z
    return T


def _xyz(v: Any) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=np.float64)


def _rows_xyz(vs: list[Any]) -> np.ndarray:
    """(M, 3) float64 of the vectors' x, y, z: ``np.array([_xyz(v) for v in vs])`` without
    a small array per vector."""
    return np.array([[v.x, v.y, v.z] for v in vs], dtype=np.float64).reshape(len(vs), 3)


def _cloud_layout(msg: Any) -> tuple[dict[str, Any], np.dtype, np.ndarray]:
    """A PointCloud2's fields by name, its point dtype, and its points' bytes as a
    (height, width * point_step) uint8 view of the message (rows without their padding)."""
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
    return fields, dtype, rows[:, : msg.width * msg.point_step]


def decode_pointcloud2(msg: Any, topic: str, stats: ReadStats) -> LadarScan:
    """PointCloud2 -> LadarScan. Non-finite points are dropped and counted in ``stats``.

    Per-point time from a field ``t`` or ``offset_time`` (integer ns after the stamp) or
    ``time`` (float seconds after the stamp); ring from ``ring`` (or ``laser_number``).

    The same frames as ``decode_pointcloud2_reference`` (a test oracle in
    ``tests/kernel_reference``), faster: the points are viewed in
    place instead of copied first, x, y, z come out in one copy (not three field copies
    stacked and cast), and the per-point finiteness test only runs when the sweep has a
    non-finite coordinate at all.
    """
    # the same layout as the reference, so that malformed clouds raise the same errors
    fields, dtype, points = _cloud_layout(msg)
    if not points.flags.c_contiguous:  # padded rows: only a copy makes the points one array
        points = points.copy()
    # a view of the message's bytes (unaligned, read-only) or of their copy: every field
    # taken from it below is a new array, so no frame shares memory with the message
    cloud = points.view(dtype).reshape(-1)
    xyz = _xyz_float32(cloud)
    if np.isfinite(xyz).all():  # one fast contiguous pass; the per-row test only if needed
        n_bad = 0
    else:
        fin = np.isfinite(xyz)
        finite = fin[:, 0] & fin[:, 1] & fin[:, 2]
        n_bad = int(finite.size - finite.sum())
    if n_bad:
        stats.dropped_nonfinite_points += n_bad
        cloud, xyz = cloud[finite], xyz[finite]
    return _scan_of(msg, topic, cloud, xyz, fields)


def _xyz_float32(cloud: np.ndarray) -> np.ndarray:
    """(N, 3) float32 of the structured cloud's x, y, z: the values and dtype of
    ``np.stack([x, y, z], axis=1).astype(np.float32)``, in one copy into a new array.

    When x, y, z are adjacent fields of one type (as LADAR drivers lay them out), their 12
    (or 24) bytes a point are copied as one opaque field, which numpy does several times
    faster than a strided (N, 3) copy or three field copies out of unaligned records;
    otherwise each field is cast into its column. Both give the stack-and-cast's values: the
    stack widens x, y, z to a type that holds all three exactly (PointField types are at most
    32-bit integers or float64), so the only rounding is the one to float32 in both.
    """
    n = cloud.shape[0]
    (tx, ox), (ty, oy), (tz, oz) = (cloud.dtype.fields[c][:2] for c in "xyz")
    size = tx.itemsize
    if tx == ty == tz and (oy, oz) == (ox + size, ox + 2 * size):
        layout = {"names": ["xyz"], "formats": [f"V{3 * size}"], "offsets": [ox]}
        block = np.dtype({**layout, "itemsize": cloud.dtype.itemsize})
        points = cloud.view(block)["xyz"]
        if tx == np.dtype(np.float32):  # native float32: the bytes are the values
            xyz = np.empty((n, 3), np.float32)
            xyz.view(points.dtype).reshape(n)[...] = points
            return xyz
        return points.copy().view(tx).reshape(n, 3).astype(np.float32)
    xyz = np.empty((n, 3), np.float32)
    for i, c in enumerate("xyz"):
        xyz[:, i] = cloud[c]
    return xyz


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
        self._no_info: set[str] = set()  # cameras already reported without CameraInfo

    def wants(self, role: Role | None) -> bool:
        """Whether messages of ``role`` are worth deserialising for the requested kinds."""
        if role is None:
            return False
        return self.kinds is None or ROLE_KIND[role] in self.kinds

    def push(self, topic: str, role: Role, message: Any, log_t_ns: int) -> list[LogMessage]:
        """Add one message; returns the frames completed by the instant before it."""
        out: list[LogMessage] = []
        if self._pending_t is not None and log_t_ns != self._pending_t:
            out = self.flush()
        self._pending_t = log_t_ns
        self._pending.append((topic, role, message))
        return out

    def flush(self) -> list[LogMessage]:
        """Decode the messages of the pending instant."""
        batch = sorted(self._pending, key=lambda p: not _is_prerequisite(*p))
        self._pending, self._pending_t = [], None
        out: list[LogMessage] = []
        for topic, role, message in batch:
            try:
                out.extend(self._decode(topic, role, message))
            except (ValueError, KeyError, IndexError, AttributeError) as exc:
                problem = f"{topic}: cannot make a frame of a {role.value} message: {exc}"
                if self.on_error is None:
                    raise LogError(problem) from exc
                self.on_error(problem)
        return out

    def _decode(self, topic: str, role: Role, msg: Any) -> Iterable[LogMessage]:
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
            dims = msg.layout.dim
            n = int(dims[1].size) if len(dims) >= 2 and int(dims[1].size) in (3, 4) else 3
            self._velocities[frame_topic(topic, role)] = data.reshape(-1, n).copy()
            return []
        if role is Role.BOXES:
            return [self._boxes(msg, topic)]
        return self._image(msg, topic)

    def _image(self, msg: Any, topic: str) -> list[LogMessage]:
        base = frame_topic(topic, Role.IMAGE)
        t_ns = stamp_ns(msg.header)
        pixels = _image_pixels(msg)
        if _is_depth(topic, msg):
            self._depth[base] = (t_ns, pixels)
            return []
        depth = self._depth.pop(base, None)
        info = self._camera_info.get(base)
        if info is None:
            if base not in self._no_info:
                self._no_info.add(base)
                self.stats.note(f"{topic}: no CameraInfo before the image at t_ns={t_ns}; K NaN")
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
        # one array from plain lists of Python floats per field, not a small array per box
        # stacked (the values and dtypes of the tests' boxes_reference, faster)
        quats = np.array(
            [[o.x, o.y, o.z, o.w] for o in [d.bbox.center.orientation for d in dets]]
        ).reshape(m, 4)
        x, y, z, w = quats.T
        velocities, n_returns = _velocities_returns(self._velocities.pop(topic, None), m)
        return ObjectBoxes(
            t_ns=stamp_ns(msg.header),
            frame_id=msg.header.frame_id,
            ids=np.array([self._track_id(d.id) for d in dets], dtype=np.int64),
            classes=[d.results[0].hypothesis.class_id if d.results else "" for d in dets],
            centers=_rows_xyz([d.bbox.center.position for d in dets]),
            sizes=_rows_xyz([d.bbox.size for d in dets]),
            yaws=np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)),
            velocities=velocities,
            topic=topic,
            n_returns=n_returns,
        )


def _is_depth(topic: str, msg: Any) -> bool:
    return msg.encoding in _DEPTH_ENCODINGS or "depth" in topic.rsplit("/", 1)[-1]


def _is_prerequisite(topic: str, role: Role, msg: Any) -> bool:
    """Messages an instant's image or box array needs before it: infos, depth, velocities."""
    if role is Role.IMAGE:
        return _is_depth(topic, msg)
    return role in (Role.CAMERA_INFO, Role.BOX_VELOCITIES)


def _scan_of(msg: Any, topic: str, cloud: np.ndarray, xyz: np.ndarray, fields) -> LadarScan:
    """The scan of a decoded cloud: ``cloud`` (N,) structured points (the finite ones), ``xyz``
    (N, 3) float32 their coordinates, ``fields`` the message's field names; intensity, per-point
    time offsets (ns) and ring taken from whichever of their usual names the cloud carries."""
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


def _velocities_returns(rows: np.ndarray | None, m: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The boxes' velocities (m, 3) m/s and per-box LADAR returns (m,) int64 (or None) from the
    parallel array's rows (NaN velocities when it is missing or does not fit the boxes)."""
    if rows is None or rows.shape[0] != m:
        return np.full((m, 3), np.nan), None
    returns = None
    if rows.shape[1] == 4 and np.all(np.isfinite(rows[:, 3])) and np.all(rows[:, 3] >= 0):
        returns = rows[:, 3].astype(np.int64)  # a damaged count is unknown, not a number
    return np.ascontiguousarray(rows[:, :3]), returns
