"""The ground surface on the LADAR egosphere image (SP level 3 grouping, the ground hypothesis).

Reference 001, 4.5.6 (level 3 of sensory processing: "surfaces ... the ground"), 4.5.2
(grouping by continuity). The egosphere image (:mod:`sp.egosphere`) orders each column's
returns by elevation, so the ground is the run of returns that, walking up a column from the
lowest beam, rises no faster than the steepest drivable slope from the last ground return
(continuity); an object in front breaks the run (a vertical face rises with no horizontal
progress) and the ground resumes behind it only after a range gap (so the roof of a car is not
taken for ground seen over it). Slopes and curbs: the test is local, so a hill is ground all
the way up, and a curb of ``step_m`` or less is stepped over.

A second pass (``refine``) levels out mistakes with a polar grid: a return far above the
lowest ground of its cell and its neighbours is not ground; a return close to it is.

Heights are in a gravity-aligned frame centred on the sensor (``R_world_sensor`` rotates the
sensor frame's points; z up, metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np


class GroundError(ValueError):
    """An image or configuration the ground segmentation cannot use; names the value."""


@dataclass(frozen=True)
class GroundConfig:
    """Ground segmentation parameters (metres, degrees).

    sensor_height_m:   prior height of the sensor above the ground under it; each sweep
                       re-estimates it from the lowest returns, within ``height_search_m``.
    start_tol_m:       a column's first ground return lies this close to the ground plane
                       under the sensor (plus the slope allowance over its range).
    max_slope_deg:     steepest ground between successive ground returns of a column.
    step_m:            rise allowed on top of the slope (noise, curbs, ruts).
    resume_gap_m:      after a non-ground return, the ground resumes only at least this much
                       farther (plus ``resume_gap_per_m`` times the range) than it, and rising
                       no steeper than ``resume_slope_deg`` from the last ground return.
    cell_m, n_sectors: polar grid of the refinement pass (radial cell length, sectors).
    refine_above_m:    in refinement, returns this far above the local lowest ground are
                       not ground; returns within ``refine_within_m`` of it are.
    """

    sensor_height_m: float = 1.8
    height_search_m: float = 1.0
    start_tol_m: float = 0.35
    max_slope_deg: float = 32.0
    step_m: float = 0.06
    resume_gap_m: float = 0.8
    resume_slope_deg: float = 15.0
    resume_gap_per_m: float = 0.04
    refine: bool = True
    cell_m: float = 2.0
    n_sectors: int = 180
    refine_above_m: float = 0.35
    refine_within_m: float = 0.12

    def __post_init__(self) -> None:
        if not 0.0 < self.max_slope_deg < 80.0:
            raise GroundError(f"max_slope_deg {self.max_slope_deg} is not in (0, 80)")
        if self.cell_m <= 0 or self.n_sectors < 1:
            raise GroundError(f"polar grid cell_m {self.cell_m}, n_sectors {self.n_sectors}")


def estimate_sensor_height(z_m: np.ndarray, valid: np.ndarray, config: GroundConfig) -> float:
    """Height of the sensor above the ground (m) from the lowest return of every column:
    their median, kept within ``height_search_m`` of the prior. z_m, valid: (H, W)."""
    has = valid.any(axis=0)
    if not has.any():
        return config.sensor_height_m
    lowest_row = valid.shape[0] - 1 - np.argmax(valid[::-1], axis=0)
    cols = np.flatnonzero(has)
    z_low = z_m[lowest_row[cols], cols]
    h = -float(np.median(z_low))
    lo, hi = (
        config.sensor_height_m - config.height_search_m,
        config.sensor_height_m + (config.height_search_m),
    )
    return float(np.clip(h, lo, hi))


def column_walk(
    r_m: np.ndarray, z_m: np.ndarray, valid: np.ndarray, height_m: float, config: GroundConfig
) -> np.ndarray:
    """Ground mask (H, W) bool by walking every column up from its lowest beam.

    r_m: (H, W) horizontal range from the sensor, z_m: (H, W) height relative to the sensor
    (gravity-aligned), valid: (H, W) bool; row 0 is the highest elevation. One compiled pass
    (:func:`_column_walk_kernel`); :func:`column_walk_reference` is the same rule in numpy.
    """
    return _column_walk_kernel(
        np.ascontiguousarray(r_m, dtype=np.float64),
        np.ascontiguousarray(z_m, dtype=np.float64),
        np.ascontiguousarray(valid, dtype=np.bool_),
        float(height_m),
        float(np.tan(np.deg2rad(config.max_slope_deg))),
        float(np.tan(np.deg2rad(config.resume_slope_deg))),
        float(config.start_tol_m),
        float(config.step_m),
        float(config.resume_gap_m),
        float(config.resume_gap_per_m),
    )


@numba.njit(cache=True, nogil=True)
def _column_walk_kernel(r_m, z_m, valid, height_m, tan_s, tan_r, start_tol, step, gap, gap_per_m):
    """:func:`column_walk_reference` row by row, every column's walk state in scalars of
    arrays (W,): the same comparisons on the same float64 values, so the same mask."""
    H, W = r_m.shape
    ground = np.zeros((H, W), dtype=np.bool_)
    last_r = np.zeros(W)
    last_z = np.full(W, -height_m)
    have = np.zeros(W, dtype=np.bool_)
    prev_r = np.zeros(W)
    prev_ground = np.ones(W, dtype=np.bool_)
    for i in range(H - 1, -1, -1):
        for j in range(W):
            if not valid[i, j]:
                continue
            r, z = r_m[i, j], z_m[i, j]
            if not have[j]:
                g = abs(z + height_m) <= start_tol + tan_s * r
            else:
                dr = r - last_r[j]
                run = tan_s * max(dr, 0.0)
                g = (
                    dr > 0.0
                    and (z - last_z[j]) <= run + step
                    and (last_z[j] - z) <= run + step + 0.1 * dr
                    and (
                        prev_ground[j]
                        or (
                            r - prev_r[j] >= gap + gap_per_m * r
                            and (z - last_z[j]) <= tan_r * max(dr, 0.0) + step
                        )
                    )
                )
            ground[i, j] = g
            if g:
                last_r[j], last_z[j] = r, z
                have[j] = True
            prev_r[j] = r
            prev_ground[j] = g
    return ground


def column_walk_reference(
    r_m: np.ndarray, z_m: np.ndarray, valid: np.ndarray, height_m: float, config: GroundConfig
) -> np.ndarray:
    """:func:`column_walk` in plain numpy, one row of all columns at a time (the reference
    the compiled kernel is tested against)."""
    H, W = r_m.shape
    tan_s = np.tan(np.deg2rad(config.max_slope_deg))
    tan_r = np.tan(np.deg2rad(config.resume_slope_deg))
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
        drop_ok = (last_z - z) <= tan_s * np.maximum(dr, 0.0) + config.step_m + 0.1 * dr
        # the ground resumes behind an object only past a range gap, and no steeper than
        # ``resume_slope_deg`` from the ground in front of it (a car's hood seen past its
        # bumper is not ground)
        resume_ok = (r - prev_r >= config.resume_gap_m + config.resume_gap_per_m * r) & (
            (z - last_z) <= tan_r * np.maximum(dr, 0.0) + config.step_m
        )
        gap_ok = prev_ground | resume_ok
        cont = v & have & (dr > 0.0) & rise_ok & drop_ok & gap_ok
        g = start | cont
        ground[i] = g
        last_r = np.where(g, r, last_r)
        last_z = np.where(g, z, last_z)
        have |= g
        prev_r = np.where(v, r, prev_r)
        prev_ground = np.where(v, g, prev_ground)
    return ground


def refine(
    x_m: np.ndarray,
    y_m: np.ndarray,
    z_m: np.ndarray,
    valid: np.ndarray,
    ground: np.ndarray,
    config: GroundConfig,
    r_m: np.ndarray | None = None,
) -> np.ndarray:
    """Second pass on a polar grid: the lowest ground return of each cell and its 8
    neighbours is the local ground height; returns far above it are not ground, returns close
    to it are. Inputs (H, W) float64 in the gravity-aligned sensor-centred frame (``r_m`` the
    horizontal range, if the caller has it); returns (H, W) bool. Ranges and azimuths by
    numpy, the rest in one compiled kernel (:func:`_refine_kernel`); the same mask as
    :func:`refine_reference`."""
    r = np.hypot(x_m, y_m) if r_m is None else r_m
    azimuth = np.arctan2(y_m, x_m)
    return _refine_kernel(
        np.ascontiguousarray(r, dtype=np.float64),
        np.ascontiguousarray(azimuth, dtype=np.float64),
        np.ascontiguousarray(z_m, dtype=np.float64),
        np.ascontiguousarray(valid, dtype=np.bool_),
        np.ascontiguousarray(ground, dtype=np.bool_),
        float(config.cell_m),
        int(config.n_sectors),
        float(config.refine_above_m + config.cell_m * np.tan(0.25)),
        float(config.refine_above_m),
        float(config.refine_within_m),
    )


@numba.njit(cache=True, nogil=True)
def _nan_min(a, b):
    """``np.minimum`` of two floats: NaN if either is."""
    if a != a or b != b:
        return np.nan
    return a if a <= b else b


@numba.njit(cache=True, nogil=True)
def _refine_kernel(r_m, azimuth, z_m, valid, ground, cell_m, n_sectors, above_local_m,
                   above_own_m, within_m):  # fmt: skip
    """:func:`refine_reference` with its cell indices, lowest-ground scatter, 3x3 minimum
    (azimuth wraps) and tests in loops over the pixels and cells."""
    H, W = r_m.shape
    cell = np.zeros((H, W), dtype=np.int64)
    n_ring = 1
    for i in range(H):
        for j in range(W):
            ring = min(np.int64(r_m[i, j] / cell_m), 4095)
            sector = np.int64((azimuth[i, j] + np.pi) * (n_sectors / (2 * np.pi)))
            sector = min(max(sector, 0), n_sectors - 1)
            cell[i, j] = ring * n_sectors + sector
            if valid[i, j] and ring + 1 > n_ring:
                n_ring = ring + 1
    low = np.full(n_ring * n_sectors, np.inf)
    for i in range(H):
        for j in range(W):
            if valid[i, j] and ground[i, j]:
                c = cell[i, j]
                low[c] = _nan_min(low[c], z_m[i, j])
    local = np.full(n_ring * n_sectors, np.inf)
    for a in range(n_ring):
        for b in range(n_sectors):
            m = np.inf
            for da in range(a - 1, a + 2):
                if 0 <= da < n_ring:
                    for db in (b - 1, b, b + 1):
                        m = _nan_min(m, low[da * n_sectors + db % n_sectors])
            local[a * n_sectors + b] = m
    out = np.zeros((H, W), dtype=np.bool_)
    for i in range(H):
        for j in range(W):
            if not valid[i, j]:
                continue
            c = cell[i, j]
            own = low[c] if np.isfinite(low[c]) else local[c]
            z = z_m[i, j]
            keep = ground[i, j] and not (z - local[c] > above_local_m)
            keep = keep and not (z - own > above_own_m)
            out[i, j] = keep or (abs(z - own) <= within_m and np.isfinite(own))
    return out


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
    ring = np.minimum((r / config.cell_m).astype(np.int64), 4095)
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
    out = ground & ~(above_local > config.refine_above_m + config.cell_m * np.tan(0.25))
    out &= ~(above_own > config.refine_above_m)
    out |= valid & (np.abs(above_own) <= config.refine_within_m) & np.isfinite(own[c])
    return out & valid


def ground_mask(
    xyz_g: np.ndarray, valid: np.ndarray, config: GroundConfig | None = None
) -> tuple[np.ndarray, float]:
    """Ground pixels of an egosphere image and the sensor height used.

    xyz_g: (H, W, 3) float points in the gravity-aligned frame centred on the sensor (NaN where
    empty); valid: (H, W) bool. Returns ((H, W) bool ground mask, sensor height m).
    """
    cfg = config or GroundConfig()
    if xyz_g.ndim != 3 or xyz_g.shape[2] != 3 or xyz_g.shape[:2] != valid.shape:
        raise GroundError(f"xyz_g shape {xyz_g.shape} does not match valid {valid.shape}")
    x = np.where(valid, xyz_g[..., 0], 0.0).astype(np.float64)
    y = np.where(valid, xyz_g[..., 1], 0.0).astype(np.float64)
    z = np.where(valid, xyz_g[..., 2], 0.0).astype(np.float64)
    r = np.hypot(x, y)
    h = estimate_sensor_height(z, valid, cfg)
    ground = column_walk(r, z, valid, h, cfg)
    if cfg.refine and valid.any():
        ground = refine(x, y, z, valid, ground, cfg, r_m=r)
    return ground, h
