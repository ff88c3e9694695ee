"""Numpy oracle of the compiled de-skewing of :mod:`wm.poses` (tests only).

:func:`deskew_to_world_reference` is the oracle of :func:`wm.poses.deskew_to_world`: the points
split into ``bins`` time bins over the sweep, each moved by the pose at its bin's middle time.
The kernel must give the same points to rounding.
"""

from __future__ import annotations

import numpy as np

from core.geometry import transform_points
from wm.poses import PoseTrack


def deskew_to_world_reference(
    points_xyz: np.ndarray,
    t_offset_ns: np.ndarray,
    t_ns: int,
    track: PoseTrack,
    T_body_sensor: np.ndarray,
    bins: int,
) -> np.ndarray:
    """The numpy form of :func:`deskew_to_world` (same arguments, same result to rounding)."""
    off = np.asarray(t_offset_ns, dtype=np.int64)
    span = int(off.max()) if len(off) else 0
    pts = np.asarray(points_xyz, dtype=np.float64)
    if span <= 0 or bins <= 1:
        return transform_points(track.at(t_ns) @ T_body_sensor, pts)
    which = np.clip((off * bins) // (span + 1), 0, bins - 1)
    out = np.empty((len(pts), 3), dtype=np.float64)
    for b in range(bins):
        sel = which == b
        t_mid = t_ns + round((b + 0.5) * span / bins)
        out[sel] = transform_points(track.at(t_mid) @ T_body_sensor, pts[sel])
    return out
