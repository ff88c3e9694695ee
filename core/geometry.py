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

import math
from collections.abc import Mapping

import numpy as np

from core.errors import EngineError

# Frame names used by the simulator, the log readers and the engine.
WORLD = "world"  # fixed, gravity-aligned, z up
ODOM = "odom"  # fixed, drifting odometry origin
BODY = "base_link"  # vehicle body, x forward
LADAR = "ladar"  # LADAR sensor, x forward at azimuth 0
CAMERA = "camera"  # optical frame: z forward, x right, y down (REP 103 "_optical")

NS_PER_S = 1_000_000_000


class GeometryError(EngineError, ValueError):
    """A pose, rotation or quaternion that is not what its name promises."""


def mount_of(frame_id: str, mounts: Mapping[str, np.ndarray]) -> np.ndarray | None:
    """``T_body_frame`` (4, 4) of data given in ``frame_id``: the identity for ``base_link``
    itself, the log's transform ``base_link -> frame_id`` when ``mounts`` (child frame id ->
    4x4) holds one, else None (unknown)."""
    if frame_id == BODY:
        return np.eye(4)
    T = mounts.get(frame_id)
    return None if T is None else np.asarray(T, dtype=np.float64)


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
    """Unit quaternion ``(x, y, z, w)`` to a 3x3 rotation. Refuses a zero or non-finite one.

    The norm as ``np.linalg.norm`` takes it (``sqrt(q . q)``), the entries in Python floats
    (the same IEEE doubles as numpy scalars, without their per-operation cost: a log has ten
    or more poses a sweep)."""
    q = np.asarray(q_xyzw, dtype=np.float64).reshape(4)
    n = math.sqrt(q.dot(q))  # NaN or inf for a non-finite q (or one whose square overflows)
    if not 1e-12 <= n < math.inf:
        raise GeometryError(f"quaternion (x, y, z, w) = {q.tolist()} has no rotation (norm {n})")
    return np.array(_rotation_rows(*(q / n).tolist()))


def _rotation_rows(x: float, y: float, z: float, w: float) -> list[list[float]]:
    """The rows of the rotation of the unit quaternion ``(x, y, z, w)``."""
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """3x3 rotation to a unit quaternion ``(x, y, z, w)`` with ``w >= 0`` (Shepperd's method)."""
    return np.array(_quat_of(R))


def _quat_of(R: np.ndarray) -> tuple[float, float, float, float]:
    """:func:`matrix_to_quat` in Python floats (one 3x3 is too small for numpy to pay off)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(R, dtype=np.float64)[
        :3, :3
    ].tolist()
    tr = r00 + r11 + r22
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x = 0.25 * s, (r21 - r12) / s
        y, z = (r02 - r20) / s, (r10 - r01) / s
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        w, x = (r21 - r12) / s, 0.25 * s
        y, z = (r01 + r10) / s, (r02 + r20) / s
    elif r11 > r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        w, x = (r02 - r20) / s, (r01 + r10) / s
        y, z = 0.25 * s, (r12 + r21) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        w, x = (r10 - r01) / s, (r02 + r20) / s
        y, z = (r12 + r21) / s, 0.25 * s
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if w < 0:
        n = -n
    return x / n, y / n, z / n, w / n


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
    if a.ndim == 0:
        return _interpolate_one(T0, T1, float(a))
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
    return out


def _interpolate_one(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    """:func:`interpolate_pose` at one ``alpha``, the same arithmetic in Python floats."""
    x0, y0, z0, w0 = _quat_of(T0)
    x1, y1, z1, w1 = _quat_of(T1)
    d = x0 * x1 + y0 * y1 + z0 * z1 + w0 * w1
    if d < 0:
        x1, y1, z1, w1, d = -x1, -y1, -z1, -w1, -d
    if d > 0.9995:
        x, y, z, w = (x0 + a * (x1 - x0), y0 + a * (y1 - y0), z0 + a * (z1 - z0),
                      w0 + a * (w1 - w0))  # fmt: skip
    else:
        th = math.acos(d)
        c0 = math.sin((1 - a) * th) / math.sin(th)
        c1 = math.sin(a * th) / math.sin(th)
        x, y, z, w = c0 * x0 + c1 * x1, c0 * y0 + c1 * y1, c0 * z0 + c1 * z1, c0 * w0 + c1 * w1
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    t0, t1 = np.asarray(T0, dtype=np.float64)[:3, 3], np.asarray(T1, dtype=np.float64)[:3, 3]
    rows = _rotation_rows(x, y, z, w)
    for r, t in zip(rows, (t0 + a * (t1 - t0)).tolist(), strict=True):
        r.append(t)
    return np.array([*rows, [0.0, 0.0, 0.0, 1.0]])


def box_corners(center: np.ndarray, length: float, width: float, yaw: float) -> np.ndarray:
    """(4, 2) corners of a footprint box (``length`` along ``yaw``, ``width`` across, m),
    counter-clockwise, in the frame of ``center`` (its first two coordinates)."""
    u = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]]) * (length, width)
    c, s = math.cos(yaw), math.sin(yaw)
    return center[:2] + u @ np.array([[c, s], [-s, c]])


def footprint_distance(
    points_xy: np.ndarray, centers_xy: np.ndarray, sizes_lw: np.ndarray, yaws: np.ndarray
) -> np.ndarray:
    """Distance (M, N) m from each of N points to each of M oriented rectangles (0 inside)."""
    d = points_xy[None, :, :] - centers_xy[:, None, :]
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    u = np.abs(c * d[..., 0] + s * d[..., 1]) - 0.5 * sizes_lw[:, 0:1]
    w = np.abs(-s * d[..., 0] + c * d[..., 1]) - 0.5 * sizes_lw[:, 1:2]
    return np.hypot(np.maximum(u, 0.0), np.maximum(w, 0.0))
