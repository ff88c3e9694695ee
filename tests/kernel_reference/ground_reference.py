"""Numpy oracles of the compiled ground segmentation of :mod:`sp.ground` (tests only).

:func:`column_walk_reference` is the oracle of :func:`sp.ground.column_walk` (walking up each
column, a return is ground when it rises no faster than the slope plus step, falls no faster
than that plus ``GROUND_DROP_PER_M`` per metre of range, and past an object only beyond the
resume gap), :func:`refine_reference` of :func:`sp.ground.refine` (the polar-cell lowest
ground and its 3x3 minimum level out mistakes), and :func:`ground_mask_reference` of
:func:`sp.ground.ground_mask` (both passes on zero-filled coordinates). The kernels must give
the same masks and sensor height bit for bit. The shared literals are the engine module's
constants, imported here.
"""

from __future__ import annotations

import numpy as np

from sp.ground import (
    GROUND_DROP_PER_M,
    MAX_RING,
    REFINE_CELL_SLOPE_TAN,
    GroundConfig,
    GroundError,
    estimate_sensor_height,
)


def column_walk_reference(
    r_m: np.ndarray, z_m: np.ndarray, valid: np.ndarray, height_m: float, config: GroundConfig
) -> np.ndarray:
    """:func:`column_walk` in plain numpy, one row of all columns at a time (the reference
    the compiled kernel is tested against)."""
    H, W = r_m.shape
    tan_s = np.tan(np.deg2rad(config.max_slope_deg))
    tan_r = np.tan(np.deg2rad(config.resume_slope_deg))
    tan_f = np.tan(np.deg2rad(config.face_slope_deg))
    # the next valid return up each pixel's column (its range and height; NaN where none)
    next_r = np.full((H, W), np.nan)
    next_z = np.full((H, W), np.nan)
    seen_r = np.full(W, np.nan)
    seen_z = np.full(W, np.nan)
    for i in range(H):
        v = valid[i]
        next_r[i] = np.where(v, seen_r, np.nan)
        next_z[i] = np.where(v, seen_z, np.nan)
        seen_r = np.where(v, r_m[i], seen_r)
        seen_z = np.where(v, z_m[i], seen_z)
    ground = np.zeros((H, W), dtype=bool)
    last_r = np.zeros(W)  # last ground return of each column
    last_z = np.full(W, -height_m)
    have = np.zeros(W, dtype=bool)
    prev_r = np.zeros(W)  # last return of any kind, and whether it was ground
    prev_ground = np.ones(W, dtype=bool)
    for i in range(H - 1, -1, -1):
        v = valid[i]
        r, z = r_m[i], z_m[i]
        start = v & ~have & (np.abs(z + height_m) <= config.start_tol_m + tan_s * r)
        dr = r - last_r
        rise_ok = (z - last_z) <= tan_s * np.maximum(dr, 0.0) + config.step_m
        drop_ok = (last_z - z) <= tan_s * np.maximum(
            dr, 0.0
        ) + config.step_m + GROUND_DROP_PER_M * dr
        # the ground resumes behind an object only past a range gap, and no steeper than
        # ``resume_slope_deg`` from the ground in front of it (a car's hood seen past its
        # bumper is not ground)
        resume_ok = (r - prev_r >= config.resume_gap_m + config.resume_gap_per_m * r) & (
            (z - last_z)
            <= np.minimum(tan_r * np.maximum(dr, 0.0), config.resume_max_rise_m) + config.step_m
        )
        gap_ok = prev_ground | resume_ok
        cont = v & have & (dr > 0.0) & rise_ok & drop_ok & gap_ok
        g = start | cont
        # the foot of a face: the next return up rises over it steeply, not past it
        dz = next_z[i] - z
        face = (dz > config.step_m) & (dz > tan_f * (next_r[i] - r))
        g &= ~(face & (z - last_z > config.foot_rise_m))
        ground[i] = g
        last_r = np.where(g, r, last_r)
        last_z = np.where(g, z, last_z)
        have |= g
        prev_r = np.where(v, r, prev_r)
        prev_ground = np.where(v, g, prev_ground)
    return ground


def refine_reference(
    x_m: np.ndarray,
    y_m: np.ndarray,
    z_m: np.ndarray,
    valid: np.ndarray,
    ground: np.ndarray,
    config: GroundConfig,
) -> np.ndarray:
    """:func:`refine` in plain numpy (the reference the compiled kernel is tested against)."""
    r = np.hypot(x_m, y_m)
    ring = np.minimum((r / config.cell_m).astype(np.int64), MAX_RING)
    n_ring = int(ring[valid].max(initial=0)) + 1
    sector = ((np.arctan2(y_m, x_m) + np.pi) * (config.n_sectors / (2 * np.pi))).astype(np.int64)
    sector = np.clip(sector, 0, config.n_sectors - 1)
    cell = ring * config.n_sectors + sector
    low = np.full(n_ring * config.n_sectors, np.inf)
    g = valid & ground
    np.minimum.at(low, cell[g], z_m[g])
    low = low.reshape(n_ring, config.n_sectors)
    # 3x3 minimum with wrap-around in azimuth: the local ground under objects that hide it
    pad = np.pad(low, ((1, 1), (0, 0)), constant_values=np.inf)
    pad = np.concatenate([pad[:, -1:], pad, pad[:, :1]], axis=1)
    local = np.full_like(low, np.inf)
    for di in range(3):
        for dj in range(3):
            np.minimum(local, pad[di : di + n_ring, dj : dj + config.n_sectors], out=local)
    # the cell's own lowest where it has one (a 3x3 minimum on a slope sits a cell too low)
    own = np.where(np.isfinite(low), low, local).reshape(-1)
    local = local.reshape(-1)
    c = np.where(valid, cell, 0)
    above_own = z_m - own[c]
    above_local = z_m - local[c]
    out = ground & ~(above_local > config.refine_above_m + config.cell_m * REFINE_CELL_SLOPE_TAN)
    out &= ~(above_own > config.refine_above_m)
    out |= valid & (np.abs(above_own) <= config.refine_within_m) & np.isfinite(own[c])
    return out & valid


def ground_mask_reference(
    xyz_g: np.ndarray, valid: np.ndarray, config: GroundConfig | None = None
) -> tuple[np.ndarray, float]:
    """:func:`ground_mask` in plain numpy: zero-filled coordinates, :func:`np.hypot`,
    :func:`estimate_sensor_height`, :func:`column_walk_reference` and
    :func:`refine_reference` (the reference the compiled path is tested against)."""
    cfg = config or GroundConfig()
    if xyz_g.ndim != 3 or xyz_g.shape[2] != 3 or xyz_g.shape[:2] != valid.shape:
        raise GroundError(f"xyz_g shape {xyz_g.shape} does not match valid {valid.shape}")
    x = np.where(valid, xyz_g[..., 0], 0.0).astype(np.float64)
    y = np.where(valid, xyz_g[..., 1], 0.0).astype(np.float64)
    z = np.where(valid, xyz_g[..., 2], 0.0).astype(np.float64)
    r = np.hypot(x, y)
    h = estimate_sensor_height(z, valid, cfg)
    ground = column_walk_reference(r, z, valid, h, cfg)
    if cfg.refine and valid.any():
        ground = refine_reference(x, y, z, valid, ground, cfg)
    return ground, h
