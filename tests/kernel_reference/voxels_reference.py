"""Numpy oracle of the compiled kernel of :mod:`sp.voxels` (tests only).

:func:`first_per_voxel_reference` is the oracle of :func:`sp.voxels.first_per_voxel`: the index
of the first point in every occupied voxel (``floor(p / voxel_m)``), in increasing order. The
kernel must give the same indices.
"""

from __future__ import annotations

import numpy as np


def first_per_voxel_reference(points_xyz: np.ndarray, voxel_m: float) -> np.ndarray:
    """The numpy form of :func:`first_per_voxel` (same arguments, same result)."""
    pts = np.asarray(points_xyz, dtype=np.float64)
    keys = np.floor(pts * (1.0 / voxel_m)).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first).astype(np.int64)
