"""Numpy oracle of the compiled far-ground test of :mod:`sp.ground_prior` (tests only).

:func:`expected_ground_reference` is the definition of the ground the prior expects at a
point: the minimum, over the known cells of the window whose centres lie within the radius of
the point's cell centre, of (height + slope x distance); NaN where none is known.
:func:`not_ground_reference` flags the far ground returns more than ``above_m`` above it.
:func:`sp.ground_prior.not_ground`, which prunes with a dilated grid and memoises per cell,
must flag the same pixels.
"""

from __future__ import annotations

import math

import numpy as np

from sp.ground_prior import GroundPrior, GroundPriorConfig


def expected_ground_reference(
    prior: GroundPrior, xy_m: np.ndarray, radius_m: float, slope_tan: float
) -> np.ndarray:
    """(N,) float64 expected ground height (world z, m) at world points ``xy_m`` (N, 2)."""
    xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
    n, res = prior.z_m.shape[0], float(prior.resolution_m)
    ix0, iy0 = prior.origin_cell
    cell = np.floor(xy / res).astype(np.int64)
    best = np.full(len(xy), np.inf)
    k = int(radius_m // res)
    for dy in range(-k, k + 1):
        for dx in range(-k, k + 1):
            d = res * math.hypot(dx, dy)
            if d > radius_m:
                continue
            cx, cy = cell[:, 0] + dx, cell[:, 1] + dy
            inside = (cx >= ix0) & (cx < ix0 + n) & (cy >= iy0) & (cy < iy0 + n)
            z = np.full(len(xy), np.nan)
            z[inside] = prior.z_m[cy[inside] % n, cx[inside] % n]
            np.fmin(best, z + slope_tan * d, out=best)
    best[~np.isfinite(best)] = np.nan
    return best


def not_ground_reference(
    xyz_w: np.ndarray,
    range_m: np.ndarray,
    ground: np.ndarray,
    prior: GroundPrior,
    config: GroundPriorConfig,
) -> np.ndarray:
    """(H, W) bool: :func:`sp.ground_prior.not_ground` without pruning or memo."""
    slope_tan = math.tan(math.radians(config.slope_deg))
    e = expected_ground_reference(prior, xyz_w[..., :2].reshape(-1, 2), config.radius_m, slope_tan)
    above = xyz_w[..., 2] - e.reshape(ground.shape) > config.above_m  # NaN compares False
    return ground & (range_m >= config.min_range_m) & above
