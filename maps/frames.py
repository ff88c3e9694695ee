"""Rigid-body geometry, coordinate-frame names and time, shared by every floor of the engine.

Conventions (used everywhere in the engine):

* A pose is a homogeneous 4x4 float64 matrix ``T_a_b`` that maps points expressed in frame
  ``b`` into frame ``a``: ``p_a = T_a_b @ p_b``. So ``T_world_body`` is the body's pose in the
  world, and ``T_a_c = T_a_b @ T_b_c`` composes.
* Quaternions are ``(x, y, z, w)`` (the ROS order), unit norm, ``w >= 0`` on output.
* Frames are right-handed; the body frame is x forward, y left, z up (ROS REP 103).
* Lengths are metres, angles radians, times int64 nanoseconds (``t_ns``).

This module is pure numpy and imports nothing else of the engine, so the simulator, the
maps and the knowledge database can all stand on it.
"""

from __future__ import annotations

import numpy as np

# Frame names used by the simulator, the log readers and the engine.
WORLD = "world"  # fixed, gravity-aligned, z up
ODOM = "odom"  # fixed, drifting odometry origin
BODY = "base_link"  # vehicle body, x forward
LADAR = "ladar"  # LADAR sensor, x forward at azimuth 0
CAMERA = "camera"  # optical frame: z forward, x right, y down (REP 103 "_optical")

NS_PER_S = 1_000_000_000


class GeometryError(ValueError):
    """A pose, rotation or quaternion that is not what its name promises."""


def seconds_to_ns(t_s: float | np.ndarray) -> int | np.ndarray:
    """Seconds (float) to int64 nanoseconds, rounded to the nearest nanosecond."""
    if np.isscalar(t_s):
        return round(float(t_s) * NS_PER_S)
    return np.round(np.asarray(t_s, dtype=np.float64) * NS_PER_S).astype(np.int64)


def ns_to_seconds(t_ns: int | np.ndarray) -> float | np.ndarray:
    """int64 nanoseconds to float seconds."""
    if np.isscalar(t_ns):
        return int(t_ns) / NS_PER_S
    return np.asarray(t_ns, dtype=np.int64) / NS_PER_S


def se3(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """Build a 4x4 float64 pose from a 3x3 rotation ``R`` and a translation ``t`` (3,)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def se3_inverse(T_a_b: np.ndarray) -> np.ndarray:
    """Invert a rigid pose without a general matrix inverse: returns ``T_b_a``."""
    R = T_a_b[..., :3, :3]
    t = T_a_b[..., :3, 3]
    out = np.zeros_like(T_a_b, dtype=np.float64)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map points ``(N, 3)`` from frame b to frame a. Keeps the input float dtype."""
    pts = np.asarray(points_b)
    R = T_a_b[:3, :3].astype(pts.dtype if pts.dtype.kind == "f" else np.float64, copy=False)
    t = T_a_b[:3, 3].astype(R.dtype, copy=False)
    return pts @ R.T + t


def rot_x(angle: float) -> np.ndarray:
    """Rotation about x by ``angle`` radians, 3x3."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> np.ndarray:
    """Rotation about y by ``angle`` radians, 3x3."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> np.ndarray:
    """Rotation about z by ``angle`` radians, 3x3."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rpy_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Roll-pitch-yaw (fixed-axis x, y, z; i.e. ``Rz(yaw) Ry(pitch) Rx(roll)``) to a 3x3 matrix."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def matrix_to_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rpy_to_matrix` (pitch in [-pi/2, pi/2])."""
    pitch = float(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
    roll = float(np.arctan2(R[2, 1], R[2, 2]))
    yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    return roll, pitch, yaw


def yaw_of(T_or_R: np.ndarray) -> float:
    """Heading (rotation about z) of a pose or rotation, radians in (-pi, pi]."""
    R = T_or_R[:3, :3]
    return float(np.arctan2(R[1, 0], R[0, 0]))


def rotvec_of(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) of a 3x3 rotation: axis times angle in [0, pi] (the SO(3) log).

    Taken through the quaternion (Shepperd's method), which stays accurate near a half turn,
    where the trace formula's ``1 / sin(angle)`` loses precision."""
    q = matrix_to_quat(R)  # w >= 0, so the angle is in [0, pi]
    s = float(np.linalg.norm(q[:3]))
    if s < 1e-12:
        return 2.0 * q[:3]
    return q[:3] * (2.0 * np.arctan2(s, q[3]) / s)


def rotvec_to_matrix(rv: np.ndarray) -> np.ndarray:
    """3x3 rotation of a rotation vector (Rodrigues; the SO(3) exp)."""
    rv = np.asarray(rv, dtype=np.float64).reshape(3)
    angle = float(np.linalg.norm(rv))
    if angle < 1e-12:
        return np.eye(3)
    k = rv / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def quat_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` to a 3x3 rotation. Refuses a zero or non-finite one."""
    q = np.asarray(q_xyzw, dtype=np.float64).reshape(4)
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n < 1e-12:
        raise GeometryError(f"quaternion (x, y, z, w) = {q.tolist()} has no rotation (norm {n})")
    x, y, z, w = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """3x3 rotation to a unit quaternion ``(x, y, z, w)`` with ``w >= 0`` (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)[:3, :3]
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        w, x = 0.25 * s, (R[2, 1] - R[1, 2]) / s
        y, z = (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        w, x = (R[2, 1] - R[1, 2]) / s, 0.25 * s
        y, z = (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        w, x = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s
        y, z = 0.25 * s, (R[1, 2] + R[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        w, x = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s
        y, z = (R[1, 2] + R[2, 1]) / s, 0.25 * s
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def pose_from_xyz_quat(xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 pose from a translation (3,) and a quaternion (x, y, z, w)."""
    return se3(quat_to_matrix(q_xyzw), xyz)


def check_pose(T: np.ndarray, name: str = "pose", atol: float = 1e-6) -> np.ndarray:
    """Return ``T`` as float64 4x4 if it is a finite rigid transform, else raise naming it."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise GeometryError(f"{name} must be 4x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise GeometryError(f"{name} has non-finite entries: {T.tolist()}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=atol) or np.linalg.det(R) < 0:
        raise GeometryError(f"{name} rotation is not orthonormal with det +1: {R.tolist()}")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise GeometryError(f"{name} last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    return T


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, alpha: float | np.ndarray) -> np.ndarray:
    """Interpolate between two poses: linear in translation, slerp in rotation.

    ``alpha`` may be a scalar or an array (N,); the result is (4, 4) or (N, 4, 4).
    """
    a = np.asarray(alpha, dtype=np.float64)
    q0, q1 = matrix_to_quat(T0), matrix_to_quat(T1)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0[None] + a.reshape(-1, 1) * (q1 - q0)[None]
    else:
        th = np.arccos(d)
        w0 = np.sin((1 - a.reshape(-1, 1)) * th) / np.sin(th)
        w1 = np.sin(a.reshape(-1, 1) * th) / np.sin(th)
        q = w0 * q0[None] + w1 * q1[None]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    out = np.zeros((q.shape[0], 4, 4))
    out[:, 0, 0] = 1 - 2 * (y * y + z * z)
    out[:, 0, 1] = 2 * (x * y - z * w)
    out[:, 0, 2] = 2 * (x * z + y * w)
    out[:, 1, 0] = 2 * (x * y + z * w)
    out[:, 1, 1] = 1 - 2 * (x * x + z * z)
    out[:, 1, 2] = 2 * (y * z - x * w)
    out[:, 2, 0] = 2 * (x * z - y * w)
    out[:, 2, 1] = 2 * (y * z + x * w)
    out[:, 2, 2] = 1 - 2 * (x * x + y * y)
    out[:, :3, 3] = T0[:3, 3][None] + a.reshape(-1, 1) * (T1[:3, 3] - T0[:3, 3])[None]
    out[:, 3, 3] = 1.0
    return out[0] if a.ndim == 0 else out
