"""ROS message types for sensor frames: the type store, the message type names, and which
frame each message feeds (its :class:`Role`), shared by :mod:`logs.ros_encode` and
:mod:`logs.ros_decode`.

Ground-truth poses and odometry are both nav_msgs/msg/Odometry: a channel is ground truth when
its MCAP channel metadata says ``frame_kind: ground_truth_pose`` or its topic starts with
``/ground_truth`` (which is how a ROS bag, without channel metadata, tells them apart).
"""

from __future__ import annotations

import enum
from collections.abc import Iterable
from functools import cache
from typing import Any

from logs.types import (
    CameraFrame,
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    ObjectBoxes,
    OdometryFrame,
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


def frame_topics_of(topics: Iterable[tuple[str, str]]) -> set[str]:
    """Frame topics fed by stored ``(topic, msgtype)`` pairs (types frames do not carry: none)."""
    out = set()
    for topic, msgtype in topics:
        role = role_of(topic, msgtype)
        if role is not None:
            out.add(frame_topic(topic, role))
    return out
