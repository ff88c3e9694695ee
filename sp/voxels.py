"""Voxel thinning of a point cloud: the first point of each occupied voxel.

KISS-ICP samples a deskewed sweep to one point per half map voxel before it registers it and
updates its map (the first point it meets in each voxel). :func:`first_per_voxel` finds the
same points' indices in one compiled pass (an open-addressing hash of voxel keys), so a
caller can thin a sweep *before* a per-point step (deskewing) and carry the points' other
columns (per-point times) along. ``first_per_voxel_reference`` (a test oracle, in
``tests/kernel_reference``) is its numpy form (``np.unique`` over the voxel keys).
"""

from __future__ import annotations

import numba
import numpy as np

from core.errors import EngineError


class VoxelError(EngineError, ValueError):
    """Points or a voxel size that cannot be thinned (names the value)."""


def first_per_voxel(points_xyz: np.ndarray, voxel_m: float) -> np.ndarray:
    """Indices (int64, ascending) of the first point in each voxel of edge ``voxel_m``.

    points_xyz: (N, 3) finite metres, any frame (voxels are aligned to its axes, voxel
    ``floor(p / voxel_m)``): KISS-ICP's voxel down-sampling, which keeps the first point it meets
    in each voxel, in input order.
    """
    pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise VoxelError(f"points_xyz must be (N, 3) metres, got shape {pts.shape}")
    if not voxel_m > 0:
        raise VoxelError(f"voxel_m must be positive, got {voxel_m}")
    n = len(pts)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if not np.isfinite(pts).all():
        raise VoxelError("points_xyz holds NaN or inf coordinates (drop them first)")
    cap = 1 << max(int(2 * n - 1).bit_length(), 4)  # a power of two >= 2N: short probes
    return _first_per_voxel_kernel(pts, 1.0 / voxel_m, cap)


@numba.njit(cache=True, nogil=True)
def _first_per_voxel_kernel(pts, inv, cap):  # pragma: no cover
    """pts (N, 3) float64; inv = 1 / voxel edge; cap a power of two > N (table slots)."""
    mask = cap - 1
    kx = np.empty(cap, dtype=np.int64)
    ky = np.empty(cap, dtype=np.int64)
    kz = np.empty(cap, dtype=np.int64)
    used = np.zeros(cap, dtype=np.bool_)
    keep = np.empty(pts.shape[0], dtype=np.int64)
    m = 0
    for i in range(pts.shape[0]):
        x = np.int64(np.floor(pts[i, 0] * inv))
        y = np.int64(np.floor(pts[i, 1] * inv))
        z = np.int64(np.floor(pts[i, 2] * inv))
        h = (x * 73856093) ^ (y * 19349669) ^ (z * 83492791)
        s = h & mask
        seen = False
        while used[s]:
            if kx[s] == x and ky[s] == y and kz[s] == z:
                seen = True
                break
            s = (s + 1) & mask
        if not seen:  # an empty slot: a voxel met for the first time
            used[s] = True
            kx[s] = x
            ky[s] = y
            kz[s] = z
            keep[m] = i
            m += 1
    return keep[:m].copy()
