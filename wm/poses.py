"""A time-indexed track of rigid poses ``T_world_body``: interpolation, extrapolation, deskew.

Poses are 4x4 float64 ``T_a_b`` (``p_a = T_a_b @ p_b``, core.geometry); times int64 ns.
"""

from __future__ import annotations

import bisect

import numba
import numpy as np

from core.errors import EngineError
from core.geometry import interpolate_pose, se3_inverse, transform_points


class PoseError(EngineError, ValueError):
    """A pose track asked for a time it cannot answer (names the time and the span)."""


class PoseTrack:
    """Poses in time order; :meth:`at` interpolates inside the span and continues the last
    (first) motion at constant velocity up to ``max_extrapolate_ns`` beyond it."""

    def __init__(self, max_extrapolate_ns: int = 200_000_000, horizon: int = 4096) -> None:
        self.t_ns: list[int] = []
        self.poses: list[np.ndarray] = []
        self.max_extrapolate_ns = int(max_extrapolate_ns)
        self.horizon = horizon

    def __len__(self) -> int:
        return len(self.t_ns)

    def add(self, t_ns: int, T: np.ndarray) -> None:
        """Append a pose; a time not after the last one is ignored (repeated stamps)."""
        if self.t_ns and t_ns <= self.t_ns[-1]:
            return
        self.t_ns.append(int(t_ns))
        self.poses.append(np.asarray(T, dtype=np.float64))
        if len(self.t_ns) > self.horizon:
            del self.t_ns[0], self.poses[0]

    def covers(self, t_ns: int) -> bool:
        return bool(self.t_ns) and self.t_ns[0] <= t_ns <= self.t_ns[-1]

    def at(self, t_ns: int) -> np.ndarray:
        """The pose at ``t_ns`` (4x4); raises :class:`PoseError` too far outside the span."""
        ts = self.t_ns
        if not ts:
            raise PoseError(f"pose at t_ns={t_ns}: the track is empty")
        if len(ts) == 1:
            if abs(t_ns - ts[0]) <= self.max_extrapolate_ns:
                return self.poses[0]
            raise PoseError(f"pose at t_ns={t_ns}: only one pose, at {ts[0]}")
        if t_ns < ts[0] - self.max_extrapolate_ns or t_ns > ts[-1] + self.max_extrapolate_ns:
            raise PoseError(f"pose at t_ns={t_ns}: outside the track [{ts[0]}, {ts[-1]}] ns")
        i = min(max(bisect.bisect_right(ts, t_ns), 1), len(ts) - 1)
        t0, t1 = ts[i - 1], ts[i]
        return interpolate_pose(self.poses[i - 1], self.poses[i], (t_ns - t0) / (t1 - t0))

    def velocity(self, t_ns: int, dt_ns: int = 50_000_000) -> np.ndarray:
        """World-frame linear velocity (3,) m/s by a central difference over ``dt_ns``."""
        if len(self.t_ns) < 2:
            return np.zeros(3)
        lo = max(t_ns - dt_ns, self.t_ns[0])
        hi = min(t_ns + dt_ns, self.t_ns[-1])
        if hi <= lo:
            lo, hi = self.t_ns[-2], self.t_ns[-1]
        return (self.at(hi)[:3, 3] - self.at(lo)[:3, 3]) / ((hi - lo) * 1e-9)


def deskew_to_world(
    points_xyz: np.ndarray,
    t_offset_ns: np.ndarray,
    t_ns: int,
    track: PoseTrack,
    T_body_sensor: np.ndarray,
    bins: int,
) -> np.ndarray:
    """Sensor points (N, 3) of one sweep to world points (N, 3) float64, each slice of the
    sweep moved with the body pose at the slice's middle time (``bins`` slices of the span of
    ``t_offset_ns`` (N,) ns after ``t_ns``). One compiled pass over the points
    (``deskew_to_world_reference`` is its numpy form)."""
    off = np.ascontiguousarray(t_offset_ns, dtype=np.int64)
    span = int(off.max()) if len(off) else 0
    if span <= 0 or bins <= 1:
        return transform_points(track.at(t_ns) @ T_body_sensor, points_xyz).astype(np.float64)
    T = np.stack(
        [track.at(t_ns + round((b + 0.5) * span / bins)) @ T_body_sensor for b in range(bins)]
    )
    pts = np.asarray(points_xyz)
    if pts.dtype not in (np.float32, np.float64):
        pts = pts.astype(np.float64)
    out = np.empty((len(pts), 3), dtype=np.float64)
    _deskew_kernel(np.ascontiguousarray(pts), off, span, T, out)
    return out


@numba.njit(cache=True, nogil=True)
def _deskew_kernel(pts, off, span, T, out):  # pragma: no cover
    """pts (N, 3) float; off (N,) int64 ns; T (bins, 4, 4) the slices' poses; out (N, 3)."""
    bins = T.shape[0]
    for i in range(pts.shape[0]):
        b = min(max((off[i] * bins) // (span + 1), 0), bins - 1)
        x = np.float64(pts[i, 0])
        y = np.float64(pts[i, 1])
        z = np.float64(pts[i, 2])
        for k in range(3):
            out[i, k] = T[b, k, 0] * x + T[b, k, 1] * y + T[b, k, 2] * z + T[b, k, 3]


def relative(T_world_a: np.ndarray, T_world_b: np.ndarray) -> np.ndarray:
    """``T_a_b`` from two world poses."""
    return se3_inverse(T_world_a) @ T_world_b
