"""Numpy oracle of the compiled kernel of :mod:`sp.sweep_points` (tests only).

:func:`sweep_points_reference` is the oracle of :func:`sp.sweep_points.sweep_points`: the first
return of every pixel in the sensor, gravity-aligned and world frames (zero where there is
none; world by one pose per column or one for the sweep) and each row's mean elevation. The
kernel must give the same arrays.
"""

from __future__ import annotations

import numpy as np

from sp.egosphere import EgosphereImage


def sweep_points_reference(
    img: EgosphereImage, R_world_ladar: np.ndarray, T_world_cols: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The numpy form of :func:`sweep_points` (same arguments and results)."""
    valid = img.valid_first
    xyz_s = np.where(valid[..., None], img.xyz[..., 0, :], 0.0).astype(np.float64)
    xyz_g = xyz_s @ R_world_ladar.T
    T = T_world_cols
    if T.shape[0] == 1:
        xyz_w = xyz_s @ T[0, :3, :3].T + T[0, :3, 3]
    else:  # one small matmul per column: (W, H, 3) @ (W, 3, 3)'
        p_w = np.matmul(xyz_s.transpose(1, 0, 2), T[:, :3, :3].transpose(0, 2, 1))
        p_w += T[:, None, :3, 3]
        xyz_w = p_w.transpose(1, 0, 2)
    first = img.xyz[..., 0, :].astype(np.float64)
    el = np.arctan2(first[..., 2], np.hypot(first[..., 0], first[..., 1]))
    n = valid.sum(axis=1)
    s = np.where(valid, el, 0.0).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        row_el = np.where(n > 0, s / np.maximum(n, 1), np.nan)
    return xyz_s, xyz_g, xyz_w, row_el
