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

:func:`ground_mask` runs on every sweep: one compiled call gathers the valid pixels (their
coordinates, horizontal ranges, each column's lowest return), takes the sensor height and walks
the columns; numpy gives the azimuths (its arctan2, to the bit); a second compiled call refines.
Only the valid pixels are read and stored (no image-sized float copies).
``ground_mask_reference`` (a test oracle, in ``tests/kernel_reference``) is the numpy form it is
tested against (the same mask and the same height, bit for bit).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from core.errors import EngineError
from sp.nan_ops import minimum as _nan_min

# A column's ground may fall this much more per metre of range step (m/m) than it may rise,
# on top of the slope and step allowance (column walk).
GROUND_DROP_PER_M = 0.1
# In refinement the local lowest ground is a 3x3 minimum of polar cells, so it may lie a cell
# away: a return is not ground above it by ``refine_above_m`` plus one cell at this slope.
REFINE_CELL_SLOPE_TAN = np.tan(0.25)
# Highest ring index of the refinement's polar grid (rings past it share the last one), so
# far ranges cannot make the grid unbounded.
MAX_RING = 4095


class GroundError(EngineError, ValueError):
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
                       no steeper than ``resume_slope_deg`` from the last ground return and no
                       more than ``resume_max_rise_m`` above it.
                       At 3 degrees the roof of a car parked behind another is not taken
                       for ground: in a parking lot's rows the roof 1.3-1.7 m up lies 5-7
                       degrees above the ground before the first car, and the roofs of a
                       whole row then continue it as "ground" out to 40 m. Further out a
                       slope alone lets a roof in again (3 degrees over 30 m is 1.6 m), hence
                       the cap: ground hidden behind an occluder rises at most 0.8 m, less
                       than a car's roof.
                       A hillside past an occluder that rises more is left to level 4, which
                       takes a gently sloping plane for terrain. On real street scans
                       (KITTI) a gentler rule once lost cars, but only because the grouping
                       joined three cars parked nose to tail across the returns between them
                       (:mod:`sp.segments` now skips a pixel only when it is empty or an
                       occluder), and the merged piece's track then failed.
    face_slope_deg, foot_rise_m:
                       a return the walk would take for ground is the foot of a face when
                       the next return up its column rises more than ``step_m`` over it, at
                       a slope steeper than ``face_slope_deg``, and it stands more than
                       ``foot_rise_m`` above the column's last ground return. Far out the
                       ground's rows lie metres apart, so the slope test passes the lowest
                       row on a car 30-40 m away (0.5 m up, 4 m past the last ground
                       return); the row above it, at the same range, shows it is a face.
                       On development seeds (every tenth sweep of five logs), of the walk's
                       ground returns under such a face, 1 of 19 more than 1 m from every
                       object stood over 0.15 m above the last ground return, and 9677 of
                       14893 on an object did (a curb shows 0.15 m).
    cell_m, n_sectors: polar grid of the refinement pass (radial cell length, sectors).
    refine_above_m:    in refinement, returns this far above the local lowest ground are
                       not ground; returns within ``refine_within_m`` of it are.
    raised_m, raised_max_width_m, raised_continuity, raised_dropouts, raised_min_returns:
                       a piece of a row of at least ``raised_min_returns`` returns and no
                       wider than ``raised_max_width_m``, whose returns continue each other
                       (range steps under ``raised_continuity`` times the range) and whose
                       neighbours on both sides (at most ``raised_dropouts`` empty columns
                       away) lie farther, or on one side with the row empty for more
                       columns on the other up to a return farther still, stands on the
                       terrain where it is more than ``raised_m`` above the ground between
                       the column's ground in front of it and those neighbours
                       (:func:`raised_in_rows`). A curb shows 0.15 m. Far out a row meets
                       a rock 0.4-0.7 m high 0.15-0.35 m up its face. On development seeds
                       (all four worlds, 13-20; open world, 21-39) 0.2 m against 0.25 m
                       missed 75 fewer box-frames in all (default 174 -> 156, open 77 -> 68
                       and 272 -> 247) with 55 more false positives in the village (mostly
                       a second vehicle track beside a car, 1-1.2 m high) and none more
                       elsewhere; 0.15 m added false positives on the terrain's own bumps
                       (default 36 -> 61, village 2030 -> 2201, open 1 -> 32). A bump of
                       the terrain 50 m out showed as pieces of one to three returns (a 1 m
                       rock 40 m out spans four columns of 1024).
    """

    sensor_height_m: float = 1.8
    height_search_m: float = 1.0
    start_tol_m: float = 0.35
    max_slope_deg: float = 32.0
    step_m: float = 0.06
    resume_gap_m: float = 0.8
    resume_slope_deg: float = 3.0
    resume_gap_per_m: float = 0.04
    resume_max_rise_m: float = 0.8
    face_slope_deg: float = 45.0
    foot_rise_m: float = 0.15
    refine: bool = True
    cell_m: float = 2.0
    n_sectors: int = 180
    refine_above_m: float = 0.35
    refine_within_m: float = 0.12
    raised_m: float = 0.2
    raised_max_width_m: float = 5.0
    raised_continuity: float = 0.05
    raised_dropouts: int = 3
    raised_min_returns: int = 4

    def __post_init__(self) -> None:
        if not 0.0 < self.max_slope_deg < 80.0:
            raise GroundError(f"max_slope_deg {self.max_slope_deg} is not in (0, 80)")
        if not 0.0 < self.face_slope_deg <= 90.0:
            raise GroundError(f"face_slope_deg {self.face_slope_deg} is not in (0, 90]")
        if not self.foot_rise_m >= 0.0:
            raise GroundError(f"foot_rise_m {self.foot_rise_m} is not >= 0")
        if not self.resume_max_rise_m >= 0.0:  # inf: no cap; NaN would take no ground back
            raise GroundError(f"resume_max_rise_m {self.resume_max_rise_m} is not >= 0")
        if self.cell_m <= 0 or self.n_sectors < 1:
            raise GroundError(f"polar grid cell_m {self.cell_m}, n_sectors {self.n_sectors}")
        if not (self.raised_m > 0 and self.raised_max_width_m >= 0 and self.raised_continuity > 0):
            raise GroundError(
                f"raised_m {self.raised_m}, raised_max_width_m {self.raised_max_width_m}, "
                f"raised_continuity {self.raised_continuity}: need > 0, >= 0, > 0"
            )
        if self.raised_dropouts < 0 or self.raised_min_returns < 1:
            raise GroundError(
                f"raised_dropouts {self.raised_dropouts}, raised_min_returns "
                f"{self.raised_min_returns}: need >= 0, >= 1"
            )


def estimate_sensor_height(z_m: np.ndarray, valid: np.ndarray, config: GroundConfig) -> float:
    """Height of the sensor above the ground (m) from the lowest return of every column:
    their median, kept within ``height_search_m`` of the prior. z_m, valid: (H, W)."""
    has = valid.any(axis=0)
    if not has.any():  # also spares argmax an image without rows
        return config.sensor_height_m
    lowest_row = valid.shape[0] - 1 - np.argmax(valid[::-1], axis=0)
    cols = np.flatnonzero(has)
    return _height_from_lowest(z_m[lowest_row[cols], cols], config)


def _height_from_lowest(z_low: np.ndarray, config: GroundConfig) -> float:
    """:func:`estimate_sensor_height` from ``z_low`` (C,) float64 m, the lowest return's
    height of every column that has one (any order: only their median counts). The numpy
    form of :func:`_median_height`."""
    if z_low.size == 0:
        return config.sensor_height_m
    h = -float(np.median(z_low))
    lo, hi = (
        config.sensor_height_m - config.height_search_m,
        config.sensor_height_m + config.height_search_m,
    )
    return float(np.clip(h, lo, hi))


def column_walk(
    r_m: np.ndarray, z_m: np.ndarray, valid: np.ndarray, height_m: float, config: GroundConfig
) -> np.ndarray:
    """Ground mask (H, W) bool by walking every column up from its lowest beam.

    r_m: (H, W) horizontal range from the sensor, z_m: (H, W) height relative to the sensor
    (gravity-aligned), valid: (H, W) bool; row 0 is the highest elevation. One compiled pass
    over the valid pixels (:func:`_column_walk_kernel`); ``column_walk_reference`` is the
    same rule in numpy.
    """
    ok = np.ascontiguousarray(valid, dtype=np.bool_)
    ground_v = _column_walk_kernel(
        np.asarray(r_m, dtype=np.float64)[ok],
        np.asarray(z_m, dtype=np.float64)[ok],
        ok,
        float(height_m),
        *_walk_params(config),
    )
    return _to_image(ok, ground_v)


def _walk_params(config: GroundConfig) -> tuple[float, ...]:
    """The scalars of :func:`_column_walk_kernel` after ``height_m``: tangents of the slopes,
    tolerances, gaps, the resume cap (m) and the face test (a tangent, m)."""
    return (
        float(np.tan(np.deg2rad(config.max_slope_deg))),
        float(np.tan(np.deg2rad(config.resume_slope_deg))),
        float(config.start_tol_m),
        float(config.step_m),
        float(config.resume_gap_m),
        float(config.resume_gap_per_m),
        float(config.resume_max_rise_m),
        float(np.tan(np.deg2rad(config.face_slope_deg))),
        float(config.foot_rise_m),
    )


@numba.njit(cache=True, nogil=True)
def _to_image(valid, values):  # pragma: no cover
    """(H, W) bool image of ``values`` (N,) bool, one per valid pixel in row-major order
    (``valid`` (H, W) bool C-contiguous with N true pixels); False elsewhere."""
    H, W = valid.shape
    out = np.zeros((H, W), dtype=np.bool_)
    n = values.shape[0]
    if n == 0:
        return out
    out_f = out.reshape(-1)
    valid_f = valid.reshape(-1)
    # no branch on the pixel: write every one, step k at the valid ones (clamped, so the
    # pixels after the last valid one read a value they then mask off)
    k = 0
    for p in range(H * W):
        v = valid_f[p]
        out_f[p] = v & values[min(k, n - 1)]
        k += v
    return out


@numba.njit(cache=True, nogil=True)
def _row_starts(valid):  # pragma: no cover
    """(H + 1,) int64: where each row's valid pixels start among all valid pixels in row-major
    order (the last entry their number). valid: (H, W) bool."""
    H, W = valid.shape
    start = np.empty(H + 1, dtype=np.int64)
    n = 0
    for i in range(H):
        start[i] = n
        for j in range(W):
            n += valid[i, j]
    start[H] = n
    return start


@numba.njit(cache=True, nogil=True)
def _column_walk_kernel(  # pragma: no cover
    r_valid, z_valid, valid, height_m, tan_s, tan_r, start_tol, step, gap, gap_per_m, max_rise,
    tan_f, foot,
):  # fmt: skip
    """``column_walk_reference`` row by row, every column's walk state in scalars of
    arrays (W,): the same comparisons on the same float64 values, so the same mask.

    r_valid, z_valid: (N,) float64 m, the valid pixels' range and height in row-major order
    (only they are read, so the image-sized arrays need not exist); valid: (H, W) bool
    C-contiguous. Returns the mask at the valid pixels, (N,) bool in their order (what
    :func:`_refine_kernel` reads; :func:`_to_image` makes the image of it).
    """
    H, W = valid.shape
    row_start = _row_starts(valid)
    above = _next_above(valid, row_start)
    ground_valid = np.empty(r_valid.shape[0], dtype=np.bool_)
    last_r = np.zeros(W)
    last_z = np.full(W, -height_m)
    have = np.zeros(W, dtype=np.bool_)
    prev_r = np.zeros(W)
    prev_ground = np.ones(W, dtype=np.bool_)
    for i in range(H - 1, -1, -1):
        k = row_start[i]
        for j in range(W):
            if not valid[i, j]:
                continue
            r, z = r_valid[k], z_valid[k]
            if not have[j]:
                g = abs(z + height_m) <= start_tol + tan_s * r
            else:
                dr = r - last_r[j]
                run = tan_s * max(dr, 0.0)
                g = (
                    dr > 0.0
                    and (z - last_z[j]) <= run + step
                    and (last_z[j] - z) <= run + step + GROUND_DROP_PER_M * dr
                    and (
                        prev_ground[j]
                        or (
                            r - prev_r[j] >= gap + gap_per_m * r
                            and (z - last_z[j]) <= min(tan_r * max(dr, 0.0), max_rise) + step
                        )
                    )
                )
            n = above[k]
            if g and n >= 0 and z - last_z[j] > foot:
                # the foot of a face: the next return up stands over it, not past it
                dz = z_valid[n] - z
                g = not (dz > step and dz > tan_f * (r_valid[n] - r))
            ground_valid[k] = g
            k += 1
            if g:
                last_r[j], last_z[j] = r, z
                have[j] = True
            prev_r[j] = r
            prev_ground[j] = g
    return ground_valid


@numba.njit(cache=True, nogil=True)
def _next_above(valid, row_start):  # pragma: no cover
    """(N,) int64: for each valid pixel (row-major order), the index of the next valid pixel
    up its column (a lower row index), -1 where there is none."""
    H, W = valid.shape
    above = np.full(row_start[H], -1, dtype=np.int64)
    seen = np.full(W, -1, dtype=np.int64)
    for i in range(H):
        k = row_start[i]
        for j in range(W):
            if valid[i, j]:
                above[k] = seen[j]
                seen[j] = k
                k += 1
    return above


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
    to it are. Inputs (H, W) float in the gravity-aligned sensor-centred frame (m; ``r_m`` the
    horizontal range, if the caller has it); returns (H, W) bool. Ranges and the valid pixels'
    azimuths by numpy, the rest in one compiled kernel (:func:`_refine_kernel`); the same mask
    as ``refine_reference``."""
    ok = np.ascontiguousarray(valid, dtype=np.bool_)
    r = np.hypot(x_m, y_m) if r_m is None else r_m
    # only the valid pixels take part (an invalid pixel's cell is never used); numpy's
    # arctan2, as the reference: a compiled atan2 differs from it in the last bit
    r_v = np.asarray(r, dtype=np.float64)[ok]
    return _refine_kernel(
        r_v,
        np.arctan2(y_m[ok], x_m[ok]).astype(np.float64),
        np.asarray(z_m, dtype=np.float64)[ok],
        np.asarray(ground, dtype=np.bool_)[ok],
        ok,
        np.empty(r_v.size, dtype=np.int64),
        *_refine_params(config),
    )


def _refine_params(config: GroundConfig) -> tuple[float, int, float, float, float]:
    """The scalars of :func:`_refine_kernel`: cell length (m), sectors, the limits above the
    local and the cell's own lowest ground, and the band around it (m)."""
    return (
        float(config.cell_m),
        int(config.n_sectors),
        float(config.refine_above_m + config.cell_m * REFINE_CELL_SLOPE_TAN),
        float(config.refine_above_m),
        float(config.refine_within_m),
    )


@numba.njit(cache=True, nogil=True)
def _refine_kernel(  # pragma: no cover
    r_valid, az_valid, z_valid, ground_valid, valid, cell, cell_m, n_sectors, above_local_m,
    above_own_m, within_m,
):  # fmt: skip
    """``refine_reference`` with its cell indices, lowest-ground scatter, 3x3 minimum
    (azimuth wraps) and tests in loops over the valid pixels and the cells.

    r_valid, az_valid, z_valid: (N,) float64, the valid pixels' range (m), azimuth (rad) and
    height (m) in row-major order; ground_valid: (N,) bool, their ground mask; valid: (H, W)
    bool C-contiguous with N true pixels; cell: (N,) int64 scratch (overwritten: the caller
    may lend a buffer it no longer needs). Returns (H, W) bool.

    The minima are taken in another order than the reference's, so a zero may differ in sign;
    none of the tests below tells -0.0 from 0.0, so the mask is the same.
    """
    n = r_valid.shape[0]
    # the cells, by the expressions of refine_reference (so the same integers)
    n_ring = 1
    for k in range(n):
        ring = min(np.int64(r_valid[k] / cell_m), MAX_RING)
        sector = np.int64((az_valid[k] + np.pi) * (n_sectors / (2 * np.pi)))
        cell[k] = ring * n_sectors + min(max(sector, 0), n_sectors - 1)
        n_ring = max(n_ring, ring + 1)
    n_cells = n_ring * n_sectors
    # lowest ground per cell; neighbouring pixels mostly share a cell, so a run's minimum is
    # kept in a register and stored when the cell changes (no load waiting on a store)
    low = np.full(n_cells, np.inf)
    run_c = -1
    run = np.inf
    for k in range(n):
        if ground_valid[k]:
            c = cell[k]
            if c != run_c:
                if run_c >= 0:
                    low[run_c] = _nan_min(low[run_c], run)
                run_c, run = c, z_valid[k]
            else:
                run = _nan_min(run, z_valid[k])
    if run_c >= 0:
        low[run_c] = _nan_min(low[run_c], run)
    # the 3x3 minimum as a 3-sector minimum (wrapping) then a 3-ring one: the same values
    # (NaN if any of the nine is), a third of the comparisons; the ring pass in place, the
    # previous ring's sector minima kept aside
    local = np.empty(n_cells)
    for a in range(n_ring):
        base = a * n_sectors
        for b in range(n_sectors):
            bl = b - 1 if b > 0 else n_sectors - 1
            br = b + 1 if b < n_sectors - 1 else 0
            local[base + b] = _nan_min(_nan_min(low[base + bl], low[base + b]), low[base + br])
    prev = np.empty(n_sectors)
    cur = np.empty(n_sectors)
    for a in range(n_ring):
        base = a * n_sectors
        cur[:] = local[base : base + n_sectors]
        for b in range(n_sectors):
            m = cur[b]
            if a > 0:
                m = _nan_min(m, prev[b])
            if a + 1 < n_ring:
                m = _nan_min(m, local[base + n_sectors + b])
            local[base + b] = m
        prev, cur = cur, prev
    # from here ``low`` holds each cell's own lowest where it has one, else the local one
    for c in range(n_cells):
        if not np.isfinite(low[c]):
            low[c] = local[c]
    # the tests with bitwise & and | (no branches on the data)
    res = np.empty(n, dtype=np.bool_)
    for k in range(n):
        c = cell[k]
        z = z_valid[k]
        o = low[c]
        keep = ground_valid[k] & (not (z - local[c] > above_local_m)) & (not (z - o > above_own_m))
        res[k] = keep | ((abs(z - o) <= within_m) & np.isfinite(o))
    return _to_image(valid, res)


def ground_mask(
    xyz_g: np.ndarray, valid: np.ndarray, config: GroundConfig | None = None
) -> tuple[np.ndarray, float]:
    """Ground pixels of an egosphere image and the sensor height used.

    xyz_g: (H, W, 3) float points in the gravity-aligned frame centred on the sensor (m; NaN
    or anything where empty, as only valid pixels are read); valid: (H, W) bool. Returns
    ((H, W) bool ground mask, sensor height m): those of ``ground_mask_reference``.
    """
    cfg = config or GroundConfig()
    if xyz_g.ndim != 3 or xyz_g.shape[2] != 3 or xyz_g.shape[:2] != valid.shape:
        raise GroundError(f"xyz_g shape {xyz_g.shape} does not match valid {valid.shape}")
    # no-ops for the pipeline's images (C-contiguous float64 and bool)
    xyz = np.ascontiguousarray(xyz_g, dtype=np.float64)
    ok = np.ascontiguousarray(valid, dtype=np.bool_)
    # one compiled call up to the walk (each return from a nogil kernel waits for the GIL,
    # which the pipeline's log-decoding thread may hold)
    x_v, y_v, z_v, r_v, ground_v, h = _prepare_walk_kernel(
        xyz,
        ok,
        float(cfg.sensor_height_m),
        float(cfg.sensor_height_m - cfg.height_search_m),
        float(cfg.sensor_height_m + cfg.height_search_m),
        *_walk_params(cfg),
    )
    if not (cfg.refine and r_v.size):
        return _to_image(ok, ground_v), h
    # numpy's arctan2, as the reference (on AVX-512 a SIMD routine that libm's atan2, the
    # compiled one, differs from in the last bit), on contiguous (N,) arrays. Fresh memory
    # costs page faults on every sweep, so the azimuths go into x's buffer and the cells
    # into y's, neither needed any more
    azimuth = np.arctan2(y_v, x_v, out=x_v)
    cells = y_v.view(np.int64)
    return _refine_kernel(r_v, azimuth, z_v, ground_v, ok, cells, *_refine_params(cfg)), h


@numba.njit(cache=True, nogil=True)
def _prepare_walk_kernel(  # pragma: no cover
    xyz, valid, prior_m, lo_m, hi_m, tan_s, tan_r, start_tol, step, gap, gap_per_m, max_rise,
    tan_f, foot,
):  # fmt: skip
    """:func:`_prepare_kernel`, the sensor height (:func:`_median_height`) and the column walk
    (:func:`_column_walk_kernel`) in one call. Returns ``x_v, y_v, z_v, r_v`` as
    :func:`_prepare_kernel`, the ground mask of the valid pixels (N,) bool and the height m."""
    x_v, y_v, z_v, r_v, z_low = _prepare_kernel(xyz, valid)
    h = _median_height(z_low, prior_m, lo_m, hi_m)
    ground_v = _column_walk_kernel(
        r_v, z_v, valid, h, tan_s, tan_r, start_tol, step, gap, gap_per_m, max_rise, tan_f, foot
    )
    return x_v, y_v, z_v, r_v, ground_v, h


@numba.njit(cache=True, nogil=True)
def _median_height(z_low, prior_m, lo_m, hi_m):  # pragma: no cover
    """:func:`_height_from_lowest` compiled, to the bit: minus the median of ``z_low`` (C,)
    float64 m, clipped to [lo_m, hi_m]; ``prior_m`` when C is 0.

    numpy's median is the mean of the middle one or two order statistics, a sum that starts
    from +0.0 (so ``(0.0 + a) + b``, never -0.0) divided by their count; its clip keeps the
    value on a tie with a bound. Both written out here (numba's own median gives -0.0 for
    a median of -0.0, numpy's +0.0).
    """
    n = z_low.size
    if n == 0:
        return prior_m
    for z in z_low:
        if np.isnan(z):  # numpy's median is NaN then
            return np.nan
    part = np.partition(z_low, n // 2)
    upper = part[n // 2]
    if n % 2:
        median = (0.0 + upper) / 1.0
    else:  # the next lower order statistic: the largest left of the partition point
        lower = part[: n // 2].max()
        median = ((0.0 + lower) + upper) / 2.0
    h = -median
    h = lo_m if lo_m > h else h
    return hi_m if hi_m < h else h


@numba.njit(cache=True, nogil=True)
def _prepare_kernel(xyz, valid):  # pragma: no cover
    """The inputs of the ground kernels in one pass over the image.

    xyz: (H, W, 3) float64 C-contiguous, m; valid: (H, W) bool C-contiguous. Returns ``x_v,
    y_v, z_v, r_v`` (N,) float64 m, the valid pixels' coordinates and horizontal range
    ``hypot(x, y)`` in row-major order (only they are ever read: no image-sized copies), and
    ``z_low`` (C,) float64 m, the height of the lowest valid return (largest row) of every
    column that has one, in column order.
    """
    H, W = valid.shape
    n = _row_starts(valid)[H]
    x_v = np.empty(n)
    y_v = np.empty(n)
    z_v = np.empty(n)
    r_v = np.empty(n)
    z_col = np.empty(W)
    has = np.zeros(W, dtype=np.bool_)
    k = 0
    for i in range(H):
        for j in range(W):
            if not valid[i, j]:
                continue
            x, y, z = xyz[i, j, 0], xyz[i, j, 1], xyz[i, j, 2]
            x_v[k] = x
            y_v[k] = y
            z_v[k] = z
            # libm's hypot, which numpy's is too (bit for bit)
            r_v[k] = math.hypot(x, y)
            k += 1
            # rows run downwards in elevation: a column's last valid row is its lowest
            z_col[j] = z
            has[j] = True
    z_low = np.empty(W)
    m = 0
    for j in range(W):
        if has[j]:
            z_low[m] = z_col[j]
            m += 1
    return x_v, y_v, z_v, r_v, z_low[:m]


def raised_in_rows(
    xyz_g: np.ndarray, valid: np.ndarray, ground: np.ndarray, config: GroundConfig | None = None
) -> np.ndarray:
    """Returns that stand on the terrain, told by their row: (H, W) bool.

    Far out, a low rock or bush is met by one row only, and its column alone cannot tell it
    from a rise of the terrain: the column walk and the refinement take it for ground. Its
    row can. Along a row the ground's range varies smoothly; a low object is a short piece
    of the row nearer than the returns on both sides of it, which pass it and meet the
    ground behind (reference 001, 4.5.2: grouping by continuity, and a break in it). On one
    side the row may hold no return at all for more than ``raised_dropouts`` columns (a
    row near the horizon, whose beams pass the object and meet nothing within the sensor's
    range); the other side must then show the step to farther returns, and the next return
    past the empty columns must lie farther too. Such a
    piece is raised where it stands more than ``raised_m`` above the line from the ground
    in front of it (the column's nearest ground return below) to the neighbour beside it
    (the same row past the break), at its own range: on terrain, the piece, the ground in
    front and the ground beside lie on one surface. Only pieces at most
    ``raised_max_width_m`` across and of ``raised_min_returns`` returns or more count (a
    rock or a bush, not a hillside nor a bump of it), and only neighbours at most
    ``raised_dropouts`` empty columns away (a sensor drops returns, more often far out), but
    for the empty side above.
    What one row cannot tell: the crest of a mound, where it stands more than ``raised_m``
    over the ground in front, looks to it like a rock.

    The column walk may have called such a piece ground (it then is not) or not (the upper
    row on a bush whose lower row it took for ground): either way the piece stands on the
    terrain, and its segment is an object however low it stands over its column's ground.

    xyz_g: (H, W, 3) float points in the gravity-aligned frame centred on the sensor (m);
    valid, ground: (H, W) bool (:func:`ground_mask`). Returns the valid pixels found raised;
    row 0 is the highest elevation and columns wrap in azimuth.
    """
    cfg = config or GroundConfig()
    if xyz_g.ndim != 3 or xyz_g.shape[2] != 3 or xyz_g.shape[:2] != valid.shape:
        raise GroundError(f"xyz_g shape {xyz_g.shape} does not match valid {valid.shape}")
    if ground.shape != valid.shape:
        raise GroundError(f"ground shape {ground.shape} does not match valid {valid.shape}")
    return _raised_kernel(
        np.ascontiguousarray(xyz_g, dtype=np.float64),
        np.ascontiguousarray(valid, dtype=np.bool_),
        np.ascontiguousarray(ground, dtype=np.bool_),
        float(cfg.raised_continuity),
        float(cfg.raised_max_width_m),
        float(cfg.raised_m),
        int(cfg.raised_dropouts),
        int(cfg.raised_min_returns),
    )


@numba.njit(cache=True, nogil=True)
def _raised_kernel(  # pragma: no cover
    xyz, valid, ground, cont, max_width, raised, dropouts, min_returns
):
    """:func:`raised_in_rows` row by row: the row's valid columns in azimuth order, cut
    where a range step exceeds ``cont`` times the range or more than ``dropouts`` columns
    are empty; each piece of ``min_returns`` or more between two cuts to farther returns, at
    least one of them a range step, is tested return by return."""
    H, W = valid.shape
    out = np.zeros((H, W), dtype=np.bool_)
    cols = np.empty(W, dtype=np.int64)
    rng = np.empty(W)  # the horizontal range of each of them
    step = np.zeros(W, dtype=np.bool_)  # a range step after position k
    gap = np.zeros(W, dtype=np.bool_)  # empty columns after position k
    dpsi = 2.0 * np.pi / W
    for i in range(H):
        n = 0
        for j in range(W):
            if valid[i, j]:
                cols[n] = j
                rng[n] = math.hypot(xyz[i, j, 0], xyz[i, j, 1])
                n += 1
        if n < 3:
            continue
        first = -1
        for k in range(n):
            k1 = (k + 1) % n
            gap[k] = (cols[k1] - cols[k]) % W > dropouts + 1
            step[k] = not gap[k] and abs(rng[k1] - rng[k]) > cont * min(rng[k], rng[k1])
            if (gap[k] or step[k]) and first < 0:
                first = k
        if first < 0:  # a whole ring of continuous returns: no piece has neighbours
            continue
        # pieces start after each cut; walk once round from the first cut
        s = (first + 1) % n
        for _ in range(n):
            e = s
            while not (gap[e] or step[e]):
                e = (e + 1) % n
            if (e - s) % n + 1 >= min_returns:
                _test_piece(
                    xyz, valid, ground, out, cols, rng, step, i, s, e, n, dpsi, max_width, raised
                )
            s = (e + 1) % n
            if s == (first + 1) % n:
                break
    return out


@numba.njit(cache=True, nogil=True)
def _test_piece(
    xyz, valid, ground, out, cols, rng, step, i, s, e, n, dpsi, max_width, raised
):  # pragma: no cover
    """Mark the raised returns of the piece at positions ``s``..``e`` (wrapping) of row
    ``i``'s valid columns ``cols``, whose horizontal ranges are ``rng``: both its cuts
    (each a range step or a run of empty columns) must lead to farther returns, one at
    least by a range step (``step``), and it at most ``max_width`` m across."""
    before = (s - 1) % n
    # both ends are cuts; the row may be empty past one of them (its beams meet nothing
    # within range there), not past both
    if not (step[before] or step[e]):
        return
    a, b = cols[s], cols[e]
    lf, rf = cols[before], cols[(e + 1) % n]
    ra, rb, r_lf, r_rf = rng[s], rng[e], rng[before], rng[(e + 1) % n]
    if not (r_lf > ra and r_rf > rb):
        return
    span = (b - a) % valid.shape[1] + 1
    if 0.5 * (ra + rb) * span * dpsi > max_width:
        return
    H = ground.shape[0]
    k = s
    while True:
        q = cols[k]
        # the column's nearest ground return below: the ground in front of the piece
        lo = -1
        for ii in range(i + 1, H):
            if valid[ii, q] and ground[ii, q]:
                lo = ii
                break
        if lo >= 0:
            rq = rng[k]
            r0 = math.hypot(xyz[lo, q, 0], xyz[lo, q, 1])
            z0 = xyz[lo, q, 2]
            above = np.inf
            for f, rf_ in ((lf, r_lf), (rf, r_rf)):
                if rf_ > r0:
                    z_line = z0 + (xyz[i, f, 2] - z0) * (rq - r0) / (rf_ - r0)
                    above = min(above, xyz[i, q, 2] - z_line)
            out[i, q] = above > raised and above < np.inf
        if k == e:
            break
        k = (k + 1) % n
