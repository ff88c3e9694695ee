"""A sweep's egosphere points in the sensor, gravity-aligned and world frames, and the mean
elevation of each image row: the level-1 geometry every later SP level reads.

Each column of the egosphere image is moved to the world with the sensor pose at its own
firing time (``T_world_cols``, see :func:`sp.level1.column_poses`), so a static object does
not smear over a moving vehicle's sweep (reference 001, 4.5.6 level 1: "range images ...
transformed into ... world coordinates"). The gravity-aligned frame is the sensor frame turned
by the sweep's orientation (no translation): heights above the sensor, for the ground.

:func:`sweep_points` is one compiled pass over the pixels (numba);
``sweep_points_reference`` (a test oracle, in ``tests/kernel_reference``) is the
numpy form it is tested against.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from core.errors import EngineError
from sp.egosphere import EgosphereImage


class SweepPointsError(EngineError, ValueError):
    """Column poses of the wrong shape for the image; names the shape."""


def sweep_points(
    img: EgosphereImage, R_world_ladar: np.ndarray, T_world_cols: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The first return of every pixel in three frames, and each row's mean elevation.

    img:            the sweep's egosphere image (H, W pixels).
    R_world_ladar:  (3, 3) the sensor's orientation at the sweep's reference time.
    T_world_cols:   (W, 4, 4) the sensor pose at each column's firing time, or (1, 4, 4) one
                    pose for every column.

    Returns ``xyz_s, xyz_g, xyz_w`` (H, W, 3) float64 metres (sensor, gravity-aligned, world;
    zero in the sensor and gravity-aligned frames where a pixel has no return) and
    ``row_el`` (H,) float64 radians, the mean elevation of each row's returns (NaN for a row
    without returns).
    """
    valid = img.valid_first
    H, W = valid.shape
    T = np.ascontiguousarray(T_world_cols, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] not in (1, W):
        raise SweepPointsError(f"T_world_cols has shape {T.shape}, not (1, 4, 4) or ({W}, 4, 4)")
    out = [np.empty((H, W, 3)) for _ in range(3)]
    row_el = np.empty(H)
    # the first return of a pixel read from the sweep's points through its index (no
    # gathered (H, W, K, 3) copy of them)
    first = np.ascontiguousarray(img.point_index[..., 0])
    R = np.ascontiguousarray(R_world_ladar, dtype=np.float64)
    _sweep_points_kernel(img.scan_points, first, R, T, *out, row_el)
    return out[0], out[1], out[2], row_el


@numba.njit(cache=True, nogil=True)
def _sweep_points_kernel(pts, first, R, T, xyz_s, xyz_g, xyz_w, row_el):  # pragma: no cover
    """pts (N, 3) float32 the sweep's points; first (H, W) int32 each pixel's first return
    (-1: none); R (3, 3); T (1 or W, 4, 4); outputs as :func:`sweep_points`."""
    H, W = first.shape
    one = T.shape[0] == 1
    for i in range(H):
        s = 0.0
        n = 0
        for j in range(W):
            c = 0 if one else j
            p = first[i, j]
            if p >= 0:
                x = np.float64(pts[p, 0])
                y = np.float64(pts[p, 1])
                z = np.float64(pts[p, 2])
                s += math.atan2(z, math.hypot(x, y))
                n += 1
            else:
                x = 0.0
                y = 0.0
                z = 0.0
            xyz_s[i, j, 0] = x
            xyz_s[i, j, 1] = y
            xyz_s[i, j, 2] = z
            for k in range(3):
                xyz_g[i, j, k] = R[k, 0] * x + R[k, 1] * y + R[k, 2] * z
                xyz_w[i, j, k] = T[c, k, 0] * x + T[c, k, 1] * y + T[c, k, 2] * z + T[c, k, 3]
        row_el[i] = s / n if n > 0 else np.nan
