"""Numpy oracle of the compiled far-ground test of :mod:`sp.ground_prior` (tests only).

:func:`expected_ground_reference` is the definition of the ground the prior expects at a
point: the minimum, over the known cells of the window whose centres lie within the radius of
the point's cell centre, of (height + slope x distance); NaN where none is known.
:func:`above_prior_reference` codes the far ground returns more than ``above_m`` above it,
and those more than ``above_m + object_margin_m`` above it. :func:`sp.ground_prior.above_prior`,
which prunes with a dilated grid and memoises per cell, must code every pixel the same, and
:func:`sp.ground_prior.on_known_ground` mark the pixels :func:`on_known_ground_reference` does.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from sp.ground_prior import ABOVE, GROUND, OBJECT, GroundPrior, GroundPriorConfig


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


def above_prior_reference(
    xyz_w: np.ndarray,
    range_m: np.ndarray,
    ground: np.ndarray,
    prior: GroundPrior,
    config: GroundPriorConfig,
) -> np.ndarray:
    """(H, W) int8: :func:`sp.ground_prior.above_prior` without pruning or memo."""
    slope_tan = math.tan(math.radians(config.slope_deg))
    e = expected_ground_reference(prior, xyz_w[..., :2].reshape(-1, 2), config.radius_m, slope_tan)
    rise = xyz_w[..., 2] - e.reshape(ground.shape)  # NaN compares False below
    judged = ground & (range_m >= config.min_range_m)
    obj = config.above_m + config.object_margin_m
    code = np.where(rise > obj, OBJECT, np.where(rise > config.above_m, ABOVE, GROUND))
    return np.where(judged, code, GROUND).astype(np.int8)


def on_known_ground_reference(
    xyz_w: np.ndarray,
    range_m: np.ndarray,
    valid: np.ndarray,
    prior: GroundPrior,
    config: GroundPriorConfig,
) -> np.ndarray:
    """(H, W) bool: :func:`sp.ground_prior.on_known_ground` in numpy: far valid returns within
    ``on_ground_m`` of their own known cell (from ``on_ground_min_range_m`` on), whose height
    passes :func:`above_prior_reference`."""
    res = float(prior.resolution_m)
    z = np.asarray(prior.z_m)
    n = z.shape[0]
    ix0, iy0 = prior.origin_cell
    cx = np.floor(np.nan_to_num(xyz_w[..., 0]) / res).astype(np.int64)
    cy = np.floor(np.nan_to_num(xyz_w[..., 1]) / res).astype(np.int64)
    inside = (cx >= ix0) & (cx < ix0 + n) & (cy >= iy0) & (cy < iy0 + n)
    cell_z = np.where(inside, z[cy % n, cx % n], np.nan)
    with np.errstate(invalid="ignore"):
        near = np.abs(xyz_w[..., 2] - cell_z) <= config.on_ground_m  # NaN compares False
    near &= valid & (range_m >= config.on_ground_min_range_m)
    cell_xyz = np.array(xyz_w, dtype=np.float64)
    cell_xyz[..., 2] = np.where(near, cell_z, 0.0)
    cell_cfg = replace(config, min_range_m=config.on_ground_min_range_m)
    return near & (above_prior_reference(cell_xyz, range_m, near, prior, cell_cfg) == GROUND)
