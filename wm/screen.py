"""What a log frame must hold before the world-modeling node takes it: one check per kind.

:func:`check_frame` looks at one frame on its own (no state of the node): its time is an
int64-like number of nanoseconds, its arrays have the shapes and dtypes of
:mod:`logs.types`, its values are finite, its rotations are rotations, its boxes have
sizes >= 0, its camera intrinsics are a pinhole camera's (:class:`sp.camera.PinholeCamera`,
the one place those are checked). It returns why the frame must be skipped as
``"reason: detail"`` (the node counts it under ``reason``), or None. The node's own checks,
those that need its state (time order, time jumps), stay in :mod:`wm.node`.

A sweep's non-finite or absurdly far points are not a reason to skip the sweep:
:func:`finite_points` drops them, as every log reader already does
(``ReadStats.dropped_nonfinite_points``), because the rest of the sweep is a good measurement
and skipping it would leave a hole in the odometry for one bad return. A sweep left with no
point at all is skipped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from core.errors import EngineError
from core.geometry import GeometryError, check_pose
from logs.types import (
    CameraFrame,
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    LogMessage,
    ObjectBoxes,
    OdometryFrame,
    TransformFrame,
)
from sp.camera import CameraError, PinholeCamera

#: a frame time must lie within +-2^62 ns (146 years): room for the offsets added to it in
#: int64 arithmetic (sweep point times, pose interpolation) without overflow
MAX_ABS_T_NS = 2**62
#: the longest a sweep may last, first point to last (ns): a LADAR sweeps at 1 Hz or faster;
#: a longer span is a corrupt per-point time, and would keep the sweep (and every later one)
#: waiting for poses until the end of the log
MAX_SWEEP_SPAN_NS = 1_000_000_000
#: points farther than this from the sensor (m) are no LADAR return but garbage (no LADAR
#: ranges 10 km); they are dropped with the non-finite ones
MAX_POINT_RANGE_M = 10_000.0
#: a rotation may be this far from orthonormal (max abs entry of R R^T - I) and be taken:
#: float32 quaternions in real logs are off by ~1e-7, the odometry re-orthonormalises
ROTATION_ATOL = 1e-4


class _Bad(EngineError):
    """Internal: a check failed; ``args[0]`` is "reason: detail" (never leaves this module)."""


def check_frame(frame: LogMessage) -> str | None:
    """Why ``frame`` must be skipped ("reason: detail"), or None when it is fit to take
    (module docstring). Never raises for any content of a frame dataclass."""
    try:
        _time(frame.t_ns)
        _CHECKS[type(frame)](frame)
    except _Bad as bad:
        return str(bad.args[0])
    except Exception as e:  # content so odd a check itself fails: still just a bad frame
        return f"bad {type(frame).__name__}: {type(e).__name__}: {e}"
    return None


def finite_points(scan: LadarScan) -> tuple[LadarScan, int]:
    """The sweep without its non-finite points and those beyond ``MAX_POINT_RANGE_M`` (their
    intensity, time offset and ring with them), and how many were dropped; the same object
    when none was. Takes a sweep :func:`check_frame` passed."""
    pts = scan.points_xyz
    with np.errstate(over="ignore", invalid="ignore"):
        keep = np.isfinite(pts).all(axis=1) & (np.abs(pts) <= MAX_POINT_RANGE_M).all(axis=1)
    dropped = int(len(keep) - np.count_nonzero(keep))
    if dropped == 0:
        return scan, 0
    ring = None if scan.ring is None else scan.ring[keep]
    kept = dataclasses.replace(
        scan,
        points_xyz=pts[keep],
        intensity=scan.intensity[keep],
        t_offset_ns=scan.t_offset_ns[keep],
        ring=ring,
    )
    return kept, dropped


# --- pieces -----------------------------------------------------------------------------------


def _time(t: object) -> None:
    """A frame time: an integer (not a bool, not a float: float64 cannot hold epoch ns
    exactly) within +-``MAX_ABS_T_NS``."""
    if isinstance(t, bool) or not isinstance(t, int | np.integer):
        raise _Bad(f"bad time: t_ns={t!r} of type {type(t).__name__}, not an integer")
    if abs(int(t)) >= MAX_ABS_T_NS:
        raise _Bad(f"bad time: t_ns={int(t)} beyond +-2^62 ns")


def _array(
    reason: str,
    name: str,
    a: object,
    shape: tuple[int | None, ...],
    kind: str = "fi",
    nan_ok: bool = False,
) -> np.ndarray:
    """``a`` as an ndarray of ``shape`` (None: any length) and a dtype kind in ``kind``
    ('f' float, 'i'/'u' integer), finite when float (NaN allowed, for "unknown", when
    ``nan_ok``); else raise naming ``name``."""
    if not isinstance(a, np.ndarray):
        raise _Bad(f"{reason}: {name} is a {type(a).__name__}, not an array")
    if a.ndim != len(shape) or any(
        n is not None and n != m for n, m in zip(shape, a.shape, strict=True)
    ):
        want = "(" + ", ".join("N" if n is None else str(n) for n in shape) + ")"
        raise _Bad(f"{reason}: {name} of shape {a.shape}, not {want}")
    if a.dtype.kind not in kind:
        raise _Bad(f"{reason}: {name} of dtype {a.dtype}")
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        if not nan_ok or np.isinf(a).any():  # NaN may stand for "unknown", infinity never
            raise _Bad(f"{reason}: {name} has non-finite values")
    return a


def _pose(reason: str, T: object) -> None:
    try:
        check_pose(_array(reason, "T_parent_child", T, (4, 4)), "T_parent_child", ROTATION_ATOL)
    except GeometryError as e:
        raise _Bad(f"{reason}: {e}") from None


def _names(reason: str, *names: object) -> None:
    if not all(isinstance(n, str) for n in names):
        raise _Bad(f"{reason}: frame ids {names!r} are not all strings")


# --- one check per frame type ----------------------------------------------------------------


def _ladar(s: LadarScan) -> None:
    """Shapes and dtypes; non-finite points are left to :func:`finite_points`."""
    why = "bad sweep"
    if not isinstance(s.points_xyz, np.ndarray):
        raise _Bad(f"{why}: points_xyz is a {type(s.points_xyz).__name__}, not an array")
    shape = s.points_xyz.shape
    if len(shape) != 2 or shape[1] != 3:
        raise _Bad(f"{why}: points_xyz of shape {shape}, not (N, 3)")
    if s.points_xyz.dtype.kind != "f":
        raise _Bad(f"{why}: points_xyz of dtype {s.points_xyz.dtype}, not float")
    n = shape[0]
    if n == 0:
        raise _Bad(f"{why}: no points")
    _array(why, "intensity", s.intensity, (n,))
    off = _array(why, "t_offset_ns", s.t_offset_ns, (n,), "iu")
    if max(-int(off.min()), int(off.max())) > MAX_SWEEP_SPAN_NS:
        raise _Bad(f"{why}: t_offset_ns spans {int(off.min())}..{int(off.max())} ns, over 1 s")
    if s.ring is not None:
        _array(why, "ring", s.ring, (n,), "iu")
    _names(why, s.frame_id)


def _camera(c: CameraFrame) -> None:
    why = "bad camera frame"
    img = c.image
    if not isinstance(img, np.ndarray) or img.dtype != np.uint8:
        raise _Bad(f"{why}: image is not a uint8 array")
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)) or 0 in img.shape:
        raise _Bad(f"{why}: image of shape {img.shape}, not (H, W) or (H, W, 3)")
    if c.depth is not None:
        if not isinstance(c.depth, np.ndarray) or c.depth.dtype.kind != "f":
            raise _Bad(f"{why}: depth is not a float array")
        if c.depth.shape != img.shape[:2]:
            raise _Bad(f"{why}: depth of shape {c.depth.shape}, image {img.shape[:2]}")
    _array(why, "K", c.K, (3, 3), "fiu")
    try:  # the intrinsics' one check (finite, focal lengths > 0, principal point, dist)
        PinholeCamera.from_frame(c)
    except CameraError as e:
        raise _Bad(f"{why}: {e}") from None
    _names(why, c.frame_id)


def _odometry(o: OdometryFrame) -> None:
    """Pose and twist; the covariances are not checked: the odometry reads an unusable one
    as unknown (sp.odometry._reported_tilt_variance)."""
    _pose("bad odometry pose", o.T_parent_child)
    _array("bad odometry twist", "twist_linear", o.twist_linear, (3,))
    _array("bad odometry twist", "twist_angular", o.twist_angular, (3,))
    _names("bad odometry pose", o.frame_id, o.child_frame_id)


def _imu(m: ImuFrame) -> None:
    why = "bad imu frame"
    _array(why, "angular_velocity", m.angular_velocity, (3,))
    _array(why, "linear_acceleration", m.linear_acceleration, (3,))
    if m.orientation_xyzw is not None:
        q = _array(why, "orientation_xyzw", m.orientation_xyzw, (4,))
        if not abs(float(np.linalg.norm(q)) - 1.0) < 1e-3:
            raise _Bad(f"{why}: orientation_xyzw of norm {np.linalg.norm(q):.4g}, not 1")
    _names(why, m.frame_id)


def _transform(t: TransformFrame) -> None:
    _pose("bad transform", t.T_parent_child)
    _names("bad transform", t.parent_frame_id, t.child_frame_id)


def _truth_pose(p: GroundTruthPose) -> None:
    _pose("bad ground-truth pose", p.T_parent_child)
    _names("bad ground-truth pose", p.frame_id, p.child_frame_id)


def _boxes(b: ObjectBoxes) -> None:
    """Every per-box array of one length M, finite (velocities may be NaN); sizes >= 0."""
    why = "bad object boxes"
    m = _array(why, "ids", b.ids, (None,), "iu").shape[0]
    if not isinstance(b.classes, list | tuple) or len(b.classes) != m:
        raise _Bad(f"{why}: {m} ids but classes is not a list of {m} names")
    if not all(isinstance(c, str) for c in b.classes):
        raise _Bad(f"{why}: classes are not all strings")
    _array(why, "centers", b.centers, (m, 3))
    sizes = _array(why, "sizes", b.sizes, (m, 3))
    if np.any(sizes < 0):
        raise _Bad(f"{why}: negative sizes {sizes[np.any(sizes < 0, axis=1)].tolist()}")
    _array(why, "yaws", b.yaws, (m,))
    # NaN is a velocity nobody measured (a track annotated once), which readers may give
    _array(why, "velocities", b.velocities, (m, 3), nan_ok=True)
    _names(why, b.frame_id)


_CHECKS: dict[type, Callable[[LogMessage], None]] = {
    LadarScan: _ladar,
    CameraFrame: _camera,
    OdometryFrame: _odometry,
    ImuFrame: _imu,
    TransformFrame: _transform,
    GroundTruthPose: _truth_pose,
    ObjectBoxes: _boxes,
}
