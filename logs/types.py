"""Log messages: what every log source yields and every log writer takes.

One dataclass per kind of message (their union is :data:`LogMessage`). Arrays are numpy with
the dtypes and shapes stated below; times are int64 nanoseconds since the epoch of the log
(``t_ns``); lengths are metres; poses are 4x4 float64 matrices ``T_parent_child`` (see
:mod:`core.geometry`).

A log source yields these in time order (by ``t_ns``); ``topic`` says where each came from.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from core.errors import EngineError


class LogError(EngineError):
    """A log that cannot be read or written as asked: names the file and what is wrong."""


@dataclass(slots=True)
class LadarScan:
    """One LADAR sweep in the sensor frame ``frame_id``.

    points_xyz:   (N, 3) float32, metres, sensor frame, finite (non-finite points are dropped
                  by readers and counted in :class:`ReadStats`).
    intensity:    (N,) float32, sensor units (reflectivity, 0..1 in the simulator).
    t_offset_ns:  (N,) int64, each point's time minus ``t_ns`` (>= 0 for a sweep stamped at
                  its start); all zero when the sensor gives no per-point times.
    ring:         (N,) uint16 beam index, or None when the sensor gives none.
    """

    t_ns: int
    frame_id: str
    points_xyz: np.ndarray
    intensity: np.ndarray
    t_offset_ns: np.ndarray
    ring: np.ndarray | None = None
    topic: str = "/ladar/points"

    @property
    def n_points(self) -> int:
        return int(self.points_xyz.shape[0])


@dataclass(slots=True)
class CameraFrame:
    """One camera image in the optical frame ``frame_id`` (z forward, x right, y down).

    image:  (H, W) uint8 intensity or (H, W, 3) uint8 RGB.
    depth:  (H, W) float32 metres along the optical axis, NaN where unknown; or None.
    K:      (3, 3) float64 pinhole intrinsics (pixels).
    dist:   (5,) float64 OpenCV plumb-bob distortion (k1, k2, p1, p2, k3); zeros for none.
    """

    t_ns: int
    frame_id: str
    image: np.ndarray
    K: np.ndarray
    depth: np.ndarray | None = None
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    topic: str = "/camera"

    @property
    def size_wh(self) -> tuple[int, int]:
        return int(self.image.shape[1]), int(self.image.shape[0])


@dataclass(slots=True)
class OdometryFrame:
    """Odometry: the pose of ``child_frame_id`` in ``frame_id`` and its velocity.

    T_parent_child:     (4, 4) float64 pose.
    twist_linear:       (3,) float64 m/s in the child frame.
    twist_angular:      (3,) float64 rad/s in the child frame.
    pose_covariance:    (6, 6) float64 (x, y, z, roll, pitch, yaw), as in nav_msgs/Odometry.
    twist_covariance:   (6, 6) float64.
    """

    t_ns: int
    frame_id: str
    child_frame_id: str
    T_parent_child: np.ndarray
    twist_linear: np.ndarray = field(default_factory=lambda: np.zeros(3))
    twist_angular: np.ndarray = field(default_factory=lambda: np.zeros(3))
    pose_covariance: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    twist_covariance: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    topic: str = "/odom"


@dataclass(slots=True)
class ImuFrame:
    """Inertial measurement in ``frame_id``.

    orientation_xyzw: (4,) float64 or None when the IMU gives none.
    angular_velocity: (3,) float64 rad/s.  linear_acceleration: (3,) float64 m/s^2.
    """

    t_ns: int
    frame_id: str
    angular_velocity: np.ndarray
    linear_acceleration: np.ndarray
    orientation_xyzw: np.ndarray | None = None
    topic: str = "/imu"


@dataclass(slots=True)
class TransformFrame:
    """One transform ``T_parent_child`` valid from ``t_ns`` (from /tf, or /tf_static)."""

    t_ns: int
    parent_frame_id: str
    child_frame_id: str
    T_parent_child: np.ndarray
    static: bool = False
    topic: str = "/tf"


@dataclass(slots=True)
class ObjectBoxes:
    """Ground-truth (or detected) 3D boxes in ``frame_id`` at ``t_ns``.

    ids:         (M,) int64 track ids, stable over time.
    classes:     list of M class names ("vehicle", "person", "building", ...).
    centers:     (M, 3) float64 box centres, metres.
    sizes:       (M, 3) float64 full extents along the box's own x, y, z, metres.
    yaws:        (M,) float64 heading about z, radians.
    velocities:  (M, 3) float64 m/s in ``frame_id``; NaN where unknown (a track annotated
                 once has no difference to take).
    n_returns:   (M,) int64 returns of the LADAR sweep starting at ``t_ns`` that hit each
                 object (ground truth per return, as a labelled point cloud gives it), or
                 None when the log does not say.
    """

    t_ns: int
    frame_id: str
    ids: np.ndarray
    classes: list[str]
    centers: np.ndarray
    sizes: np.ndarray
    yaws: np.ndarray
    velocities: np.ndarray
    topic: str = "/ground_truth/objects"
    n_returns: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass(slots=True)
class GroundTruthPose:
    """The true pose of ``child_frame_id`` (the body) in ``frame_id`` (the world)."""

    t_ns: int
    frame_id: str
    child_frame_id: str
    T_parent_child: np.ndarray
    topic: str = "/ground_truth/pose"


#: Any message a log source yields or a log writer takes (the union of the dataclasses above).
LogMessage = (
    LadarScan
    | CameraFrame
    | OdometryFrame
    | ImuFrame
    | TransformFrame
    | ObjectBoxes
    | GroundTruthPose
)

#: Deprecated alias of :data:`LogMessage`, kept so that users' code importing it still runs;
#: "frame" in the engine means a coordinate frame or a KD frame, so the engine does not use it.
Frame = LogMessage


@dataclass(slots=True)
class ReadStats:
    """What a reader had to leave out or report while reading a log."""

    skipped_records: int = 0  # corrupt or undecodable records skipped (skip_corrupt=True)
    dropped_nonfinite_points: int = 0  # NaN/inf LADAR points dropped
    backwards_timestamps: int = 0  # records whose time went backwards on their topic
    messages: list[str] = field(default_factory=list)  # one line per problem, for the user
    #: messages left out, per reason ("corrupt chunk", "duplicated chunk", ...): each skipped
    #: record counted once (however many passes meet it), as the messages it held where the
    #: log says how many (a chunk's message indexes), else 0 (the record is still counted in
    #: ``skipped_records``)
    lost: dict[str, int] = field(default_factory=dict)

    def note(self, message: str, limit: int = 100) -> None:
        if len(self.messages) < limit:
            self.messages.append(message)
