"""SP level 1 of one LADAR sweep: its egosphere image and the image's points in the sensor,
gravity-aligned and world frames (reference 001, 4.5.6 level 1: "range images ...
transformed into ... world coordinates"; 4.4.4, the image as the grid every later level's
entity image lies on).

:class:`PixelLevel` holds level 1's one piece of state, the previous sweep's pose, for the
deskew: each column of the image, which fired at its own time, goes to the world with the
sensor pose at that time, interpolated (or extrapolated) at constant velocity between the
previous sweep's pose and this one (:func:`column_poses`), so a static object does not smear
or jump by the vehicle's motion during the sweep (up to a metre at 10 m/s). The first sweep,
or one after a gap of more than ``deskew_max_gap_s``, is taken at the one pose. A caller that
deskewed the sweep itself (the world model's node, on its pose track) gives those points
instead, and every pixel takes its return's point from them, so SP and the maps see the same
points.

The egosphere takes a sweep's ``ring`` for its row, so the rings must run in elevation order.
Drivers differ: a Velodyne's ROS driver numbers them so, an Ouster numbers them from the
top, and a raw ``laser_number`` is the firing order, which interleaves elevations. Level 1
checks the first sweep that has rings: when their median elevations do not run the way the
egosphere expects (``ring_zero_at_bottom``), every ring is given the row of its rank in
elevation (:func:`ring_rows`) from then on.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from core.errors import EngineError
from core.geometry import interpolate_pose
from logs.types import LadarScan
from sp.context import SPConfig
from sp.egosphere import EgosphereImage, to_egosphere
from sp.sweep_points import sweep_points

__all__ = ["PixelLevel", "PixelLevelError", "PixelsObserved", "column_poses", "ring_rows"]

# Rings whose median elevations differ by less than this (rad) may come in either order: the
# two units of a stacked pair share elevations to a few hundredths of a degree.
RING_TIE_RAD = float(np.deg2rad(0.1))


class PixelLevelError(EngineError, ValueError):
    """Deskewed points that do not match the sweep; names their shape and the sweep's size."""


@dataclass
class PixelsObserved:
    """Level 1 of one sweep, on the egosphere grid (H, W) of ``img`` (first returns).

    img:      the sweep's egosphere image (:class:`~sp.egosphere.EgosphereImage`).
    valid:    (H, W) bool, the pixel has a return.
    xyz_s:    (H, W, 3) float64 m, sensor frame (zero where no return).
    xyz_g:    (H, W, 3) float64 m, gravity-aligned sensor frame: the sensor frame turned by
              the sweep's orientation, no translation (zero where no return).
    xyz_w:    (H, W, 3) float64 m, world frame, each column at its own pose or the caller's
              deskewed point.
    row_el:   (H,) float64 rad, mean elevation of each row's returns (NaN for an empty row).
    range_m:  (H, W) float32 m, nearest range per pixel, inf where no return.
    """

    img: EgosphereImage
    valid: np.ndarray
    xyz_s: np.ndarray
    xyz_g: np.ndarray
    xyz_w: np.ndarray
    row_el: np.ndarray
    range_m: np.ndarray


class PixelLevel:
    """Level 1: a sweep to its egosphere image and points, with the previous sweep's pose
    kept for the constant-velocity deskew (module docstring)."""

    def __init__(self, config: SPConfig) -> None:
        self.config = config
        self._last_pose: tuple[int, np.ndarray] | None = None  # (pose_t_ns, T_world_ladar)
        # ring -> row when the sensor's rings are not in elevation order; checked once
        self._ring_rows: np.ndarray | None = None
        self._rings_checked = False

    def step(
        self,
        scan: LadarScan,
        T_world_ladar: np.ndarray,
        pose_t_ns: int,
        points_world: np.ndarray | None = None,
    ) -> PixelsObserved:
        """Level 1 of ``scan`` (points in the sensor frame). ``T_world_ladar`` (4, 4) float64
        is the sensor pose at ``pose_t_ns`` (ns). ``points_world`` (N, 3) float m: the
        sweep's points already deskewed into the world by the caller, in the scan's order;
        None: each column is deskewed here (:func:`column_poses`). Raises
        :class:`PixelLevelError` when ``points_world`` does not match the sweep."""
        img = to_egosphere(self._in_elevation_order(scan), self.config.egosphere)
        valid = img.valid_first
        if points_world is None:
            T_cols = self._column_poses(img, int(scan.t_ns), T_world_ladar, pose_t_ns)
        else:  # the caller's deskew: the maps' points and SP's are the same points
            self._last_pose, T_cols = (pose_t_ns, T_world_ladar), T_world_ladar[None]
        xyz_s, xyz_g, xyz_w, row_el = sweep_points(img, T_world_ladar[:3, :3], T_cols)
        if points_world is not None:
            _place(xyz_w, img, points_world, scan.n_points)
        range_m = np.where(valid, img.range_first, np.inf)
        return PixelsObserved(img, valid, xyz_s, xyz_g, xyz_w, row_el, range_m)

    def _in_elevation_order(self, scan: LadarScan) -> LadarScan:
        """``scan`` with its rings renumbered by elevation when the first sweep with rings
        showed them out of order (module docstring); else ``scan`` itself."""
        if scan.ring is None or not self.config.egosphere.use_ring:
            return scan
        if not self._rings_checked:
            self._rings_checked = True
            self._ring_rows = ring_rows(
                scan.points_xyz, scan.ring, self.config.egosphere.ring_zero_at_bottom
            )
        if self._ring_rows is None:
            return scan
        ring = np.asarray(scan.ring, dtype=np.int64)
        known = ring < self._ring_rows.size  # a ring the first sweep lacked keeps its number
        rows = np.where(known, self._ring_rows[np.where(known, ring, 0)], ring)
        return replace(scan, ring=rows.astype(np.uint16))

    def _column_poses(
        self, img: EgosphereImage, t_ns: int, T_world_ladar: np.ndarray, pose_t_ns: int
    ) -> np.ndarray:
        """(W, 4, 4) sensor pose at each column's firing time, through the last sweep's pose
        and this one; (1, 4, 4) this pose alone for the first sweep or after a gap."""
        last, self._last_pose = self._last_pose, (pose_t_ns, T_world_ladar)
        gap_ns = pose_t_ns - last[0] if last is not None else 0
        if last is None or not 0 < gap_ns <= self.config.deskew_max_gap_s * 1e9:
            return T_world_ladar[None]
        return column_poses(img, t_ns, last[1], last[0], T_world_ladar, pose_t_ns)


def ring_rows(
    points_xyz: np.ndarray, ring: np.ndarray, zero_at_bottom: bool = True
) -> np.ndarray | None:
    """The row of each ring number (R,) int64, R = max ring + 1, when the rings of one sweep
    are not in elevation order, else None.

    points_xyz (N, 3) m in the sensor frame, ring (N,) its beam numbers. Each ring's median
    elevation ranks it, the lowest first when ``zero_at_bottom``, else the highest: the k-th
    ring so ranked takes the k-th smallest number present, and rings without a return keep
    theirs. Order is judged up to ties of ``RING_TIE_RAD``, so a sensor already in order is
    left alone.
    """
    xyz = np.asarray(points_xyz, dtype=np.float64)
    r = np.asarray(ring, dtype=np.int64)
    if r.size == 0:
        return None
    elevation = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))
    order = np.lexsort((elevation, r))
    rings, first, count = np.unique(r[order], return_index=True, return_counts=True)
    median = 0.5 * (
        elevation[order[first + (count - 1) // 2]] + elevation[order[first + count // 2]]
    )
    up = median if zero_at_bottom else -median
    if np.all(np.diff(up) > -RING_TIE_RAD):
        return None
    # the ring k-th in elevation takes the k-th of the numbers present; the others stay
    rows = np.arange(int(rings[-1]) + 1, dtype=np.int64)
    rows[rings[np.argsort(up, kind="stable")]] = rings
    return rows


def _place(xyz_w: np.ndarray, img: EgosphereImage, points_world: np.ndarray, n: int) -> None:
    """Overwrite the world point (H, W, 3) of every pixel with a return by the caller's
    deskewed point of that return (``points_world`` (n, 3) m, the scan's order)."""
    pw = np.asarray(points_world)
    if pw.shape != (n, 3):
        raise PixelLevelError(f"points_world has shape {pw.shape}; the sweep has {n} points")
    first = img.point_index[..., 0]
    if xyz_w.flags.c_contiguous:  # through a flat view: faster than the (H, W) mask
        has = np.flatnonzero(first >= 0)
        xyz_w.reshape(-1, 3)[has] = pw.take(first.reshape(-1)[has], axis=0)
    else:
        has = first >= 0
        xyz_w[has] = pw[first[has]]


def column_poses(
    img: EgosphereImage,
    t_ns: int,
    T_world_prev: np.ndarray,
    t_prev_ns: int,
    T_world_ladar: np.ndarray,
    pose_t_ns: int,
) -> np.ndarray:
    """(W, 4, 4) float64 sensor pose in the world at each column's firing time (the mean
    time of its returns, ``t_ns`` + offset, ns), at constant velocity through the two poses
    ``T_world_prev`` at ``t_prev_ns`` and ``T_world_ladar`` at ``pose_t_ns`` (slerp,
    extrapolated past ``pose_t_ns`` when the column fired later)."""
    v = img.valid_first
    off = np.where(v, img.t_offset_ns[..., 0], 0).sum(axis=0, dtype=np.float64)
    mid = off / np.maximum(v.sum(axis=0), 1)
    alpha = (t_ns + mid - t_prev_ns) / float(pose_t_ns - t_prev_ns)
    return interpolate_pose(T_world_prev, T_world_ladar, alpha.astype(np.float64))
