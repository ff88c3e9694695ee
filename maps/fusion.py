"""Point fusion: world-frame LADAR points update each cell's layers by recursive estimation.

Each cell's ground height is a scalar Kalman filter (reference 001, 4.5.4 recursive
estimation: ``x(t|t) = x*(t|t-1) + K(t) (y(t) - y*(t|t-1))``). The measurements of one sweep
falling in one cell are first combined by inverse-variance weighting (``W = sum 1/sigma_i^2``,
``z_bar = sum(z_i / sigma_i^2) / W``, ``R = 1 / W``) and then applied in one update
``K = P / (P + R)``, ``x += K (z_bar - x)``, ``P = (1 - K) P``. With no process noise this is
exactly the same as updating point by point, in any order.

Per-point variance grows with range: ``sigma = sigma0 + k * range`` (:func:`range_variance`).

A point more than ``obstacle_height_m`` above the cell's ground reference is an obstacle
point. The reference is the current estimate plus three of its standard deviations; in a
cell seen for the first time it is the lowest point of this sweep there, or the lowest ground
of a neighbouring cell plus a slope allowance when that is lower (so a cell that only saw an
object's face is not taken for ground). An obstacle point raises the occupancy log-odds and
the cell's max height but not the ground estimate. A cell with ground points and no obstacle
point this sweep lowers its log-odds. Given the sensor position (``ray_origin_xyz``), the
cells the beams cross before their returns are lowered too (:func:`cast_rays`: free space,
once per cell and sweep, an obstacle point's hit winning); without it only cells with points
change.

Two implementations give the same layers: single-pass compiled kernels (:mod:`maps.kernels`,
the default: two passes over the points and one over the touched cells) and the numpy
reference (``FusionConfig(compiled=False)``), kept as the definition the kernels are tested
against. In the numpy path each point's cell gets a row among the sweep's touched cells (a
per-level dense lookup, never cleared: only touched entries are read), and ``np.bincount`` /
``np.minimum.at`` scatter into compact (M,) arrays that stay in cache. In both, the
per-sweep sufficient statistics of a level (:class:`CellBatch`) are additive, so a finer level
hands them to the next coarser one (see :mod:`maps.stack`) and no point is counted twice.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field, replace

import numpy as np

from core.errors import EngineError
from maps import kernels
from maps.level import MapLevel

FUSION_LAYERS = (
    "elevation",
    "elevation_var",
    "elevation_min",
    "elevation_max",
    "count",
    "obstacle_count",
    "z_weight",
    "z_mean",
    "z_sq_dev_sum",
    "roughness",
    "occupancy",
    "confidence",
    "last_seen_ns",
)


class FusionError(EngineError, ValueError):
    """Points, variances or labels that cannot be fused (names the offending value)."""


@dataclass(frozen=True)
class FusionConfig:
    """How points become cell estimates. Lengths metres, variances m^2, log-odds unitless."""

    sigma0_m: float = 0.02  # range noise at zero range
    sigma_per_m: float = 0.001  # extra range noise per metre of range
    obstacle_height_m: float = 0.3  # above the ground reference -> obstacle point
    max_ground_slope: float = 0.5  # rise per run a neighbouring ground cell may differ by
    process_var_m2: float = 0.0  # added to a cell's variance before each sweep's update
    l_hit: float = 0.85  # log-odds added when a cell holds obstacle points this sweep
    l_miss: float = -0.4  # log-odds added when it holds only ground points
    l_min: float = -4.0
    l_max: float = 4.0
    confidence_var_m2: float = 0.01  # elevation variance at which confidence is 0.5
    compiled: bool = True  # numba kernels (maps.kernels); False: the numpy reference path
    ray_max_range_m: float = 40.0  # free space is traced this far along a beam (horizontal)
    ray_free_height_m: float = 0.3  # a beam this low over a cell's ground frees it (an
    # obstacle's height: a beam passing higher says nothing about a low obstacle there)
    ray_stride: int = 1  # trace every k-th beam of a sweep (at least)
    # and at most this many beams a sweep (None: all): a denser sweep traces every k-th, since
    # neighbouring beams cross the same cells (the free space of a 64 x 1024 sweep traced at
    # stride 2 misses few of the cells that every beam would free)
    ray_max_beams: int | None = 24_576
    ray_stop_after_cells: int = 8  # a walk ends after this many settled cells in a row (0: never)


def range_variance(ranges_m: np.ndarray, config: FusionConfig) -> np.ndarray:
    """Per-point height variance (m^2, float64) from range (m): ``(sigma0 + k r)^2``."""
    r = np.asarray(ranges_m, dtype=np.float64)
    return (config.sigma0_m + config.sigma_per_m * r) ** 2


@dataclass
class CellBatch:
    """One sweep's sufficient statistics per touched cell of one level (all arrays (M,)).

    ``ix, iy`` global cell indices (int64) of the level that made the batch, at
    ``resolution_m``; ground points give ``w = sum 1/var``, ``wz = sum (z - z_ref)/var``,
    ``wzz = sum (z - z_ref)^2/var`` and their number ``n``; all points give ``z_min, z_max``;
    obstacle points their number ``n_obstacle``. ``z_ref`` (m) is one scalar per sweep.
    ``reset`` marks cells of this level whose ground estimate the sweep refuted.
    """

    resolution_m: float
    z_ref: float
    ix: np.ndarray
    iy: np.ndarray
    w: np.ndarray
    wz: np.ndarray
    wzz: np.ndarray
    n: np.ndarray
    n_obstacle: np.ndarray
    z_min: np.ndarray
    z_max: np.ndarray
    reset: np.ndarray | None = None  # (M,) bool: the level's estimate there was refuted
    flat: np.ndarray | None = None  # (M,) int64 storage indices in the level that made it

    def __len__(self) -> int:
        return int(self.ix.shape[0])


@dataclass
class FusionStats:
    """What one fusion call did. ``points_in`` given, ``dropped_nonfinite`` NaN/inf points
    (or non-positive variances) left out, ``outside`` points beyond every window; per level
    name: ``ground`` / ``obstacle`` points in that level's window (raw or via finer levels)
    and ``cells_updated``."""

    points_in: int = 0
    dropped_nonfinite: int = 0
    outside: int = 0
    ground: dict[str, int] = field(default_factory=dict)
    obstacle: dict[str, int] = field(default_factory=dict)
    cells_updated: dict[str, int] = field(default_factory=dict)
    cells_freed: dict[str, int] = field(default_factory=dict)  # lowered by ray casting


@dataclass(frozen=True)
class PointColumns:
    """Points as contiguous float64 columns (N,): world ``x, y, z`` metres and ``var`` m^2.

    Columns rather than an (N, 3) array: selecting rows of 1-D arrays is several times faster.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    var: np.ndarray

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def subset(self, keep: np.ndarray) -> PointColumns:
        return PointColumns(self.x[keep], self.y[keep], self.z[keep], self.var[keep])


def clean_points(
    points_xyz: np.ndarray, variance_m2: np.ndarray | float, stats: FusionStats
) -> PointColumns:
    """Check shapes, drop non-finite points (counted in ``stats``), split into columns."""
    pts = np.asarray(points_xyz)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FusionError(f"points_xyz must be (N, 3) world metres, got shape {pts.shape}")
    n = int(pts.shape[0])
    var = np.asarray(variance_m2, dtype=np.float64)
    if var.ndim and var.shape != (n,):
        raise FusionError(f"variance_m2 must be a scalar or ({n},), got shape {var.shape}")
    xyz = np.array(pts.T, dtype=np.float64, order="C")  # one transposing copy
    var = np.full(n, float(var)) if var.ndim == 0 else np.ascontiguousarray(var)
    cols = PointColumns(xyz[0], xyz[1], xyz[2], var)
    stats.points_in += n
    if n and np.isfinite(xyz.sum() + var.sum()) and var.min() > 0:
        return cols  # one reduction settles the common case: NaN/inf would have propagated
    ok = np.isfinite(cols.x + cols.y + cols.z + cols.var) & (cols.var > 0)
    if not ok.all():
        stats.dropped_nonfinite += n - int(np.count_nonzero(ok))
        cols = cols.subset(ok)
    return cols


def window_cells(
    level: MapLevel, points: PointColumns
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Global cells ``(ix, iy)`` (int64) of ``points`` and the mask of those in the window."""
    size = level.size
    ix = np.floor(points.x / level.resolution_m).astype(np.int64)
    iy = np.floor(points.y / level.resolution_m).astype(np.int64)
    inside = ((ix - level.origin_cell[0]).view(np.uint64) < size) & (
        (iy - level.origin_cell[1]).view(np.uint64) < size
    )  # negative offsets wrap to huge unsigned values
    return ix, iy, inside


def summarise(
    level: MapLevel,
    points: PointColumns,
    config: FusionConfig,
    z_ref: float,
    child: CellBatch | None = None,
    cells: tuple[np.ndarray, np.ndarray] | None = None,
) -> CellBatch:
    """Per-cell statistics of ``points`` (those inside the window) plus a finer level's batch.

    Points must be finite; points outside the window are ignored, unless ``cells`` gives
    their global cells ``(ix, iy)`` from :func:`window_cells`, all inside. The child batch's
    cells are attributed to the cell holding their centre (exact when resolutions nest by an
    integer ratio).
    """
    size = level.size
    z, var = points.z, points.var
    if cells is None:
        ix, iy, inside = window_cells(level, points)
        if not inside.all():
            ix, iy, z, var = ix[inside], iy[inside], z[inside], var[inside]
    else:
        ix, iy = cells
    flat = storage_flat(level, ix, iy)
    z = z - z_ref
    idx = flat
    if child is not None and len(child):
        cflat = _child_flat(level, child)
        ok = cflat >= 0
        cflat = cflat[ok]
        idx = np.concatenate([flat, cflat])
    # The touched cells (in storage order) and each entry's row among them: the per-cell
    # sums go to small arrays that stay in cache and need no clearing afterwards.
    sc = _scratch(level)
    touched, row = sc.rows(idx)
    m, n_raw = len(touched), len(flat)
    raw = row[:n_raw]

    # ground reference: the current estimate (+3 sigma), else the lowest point of this sweep
    # in the cell or, lower still, in a neighbouring cell (+ a slope allowance)
    z_lo = np.full(m, np.inf)
    np.minimum.at(z_lo, raw, z)
    seen = z_lo < np.inf  # cells with raw points (the others only have the child's sums)
    gate_seen, stale = _ground_gate(level, sc, touched[seen], z_lo[seen], z_ref, config)
    gate = np.empty(m)
    gate[seen] = gate_seen
    ground = z <= gate[raw]
    w = np.where(ground, 1.0 / var, 0.0)
    wz = w * z
    parts = [w, wz, wz * z, ground.astype(np.float64), (~ground).astype(np.float64)]
    z_all = z
    if child is not None and len(child):
        cz = child.z_ref - z_ref  # re-centre the child's sums on this sweep's z_ref
        cw, cwz = child.w[ok], child.wz[ok]
        extra = [
            cw,
            cwz + cw * cz,
            child.wzz[ok] + 2.0 * cz * cwz + cw * cz * cz,
            child.n[ok].astype(np.float64),
            child.n_obstacle[ok].astype(np.float64),
        ]
        parts = [np.concatenate([a, b]) for a, b in zip(parts, extra, strict=True)]
        np.minimum.at(z_lo, row[n_raw:], child.z_min[ok] - z_ref)
        z_all = np.concatenate([z, child.z_max[ok] - z_ref])
    # scatter-sums in entry order (np.bincount adds in the same order as a loop would)
    vals = [np.bincount(row, weights=p, minlength=m) for p in parts]
    z_hi = np.full(m, -np.inf)
    np.maximum.at(z_hi, row, z_all)

    s_row, s_col = np.divmod(touched, size)
    ox, oy = level.origin_cell
    reset = np.zeros(m, dtype=bool)
    reset[np.searchsorted(touched, stale)] = True  # stale cells are among the touched ones
    return CellBatch(
        resolution_m=level.resolution_m,
        z_ref=z_ref,
        ix=ox + (s_col - ox) % size,
        iy=oy + (s_row - oy) % size,
        w=vals[0],
        wz=vals[1],
        wzz=vals[2],
        n=np.rint(vals[3]).astype(np.int64),
        n_obstacle=np.rint(vals[4]).astype(np.int64),
        z_min=z_lo + z_ref,
        z_max=z_hi + z_ref,
        reset=reset,
    )


class _Scratch:
    """Per-level dense scratch, kept at its neutral value between sweeps so a sweep touches
    only its own cells: a touched-cell mark, each touched cell's row in the sweep's compact
    arrays, and the lowest point per cell (for the neighbours' ground reference)."""

    def __init__(self, ncell: int) -> None:
        self.mark = np.zeros(ncell, dtype=np.uint8)
        self.row = np.zeros(ncell, dtype=np.intp)
        self.z_lo = np.full(ncell, np.inf)
        # compiled path: ``tag = sweep << 32 | row`` of the cells touched this sweep
        self.tag = np.zeros(ncell, dtype=np.int64)
        self.ray_stamp = np.zeros(ncell, dtype=np.int64)
        self.start_stamp = np.zeros(ncell, dtype=np.int64)
        self.start_beam = np.zeros(ncell, dtype=np.int64)
        self.order_mark = np.full(ncell, -1, dtype=np.int32)  # for storage_order
        self.sweep = 0
        self.row_ids = np.empty((3, ncell), dtype=np.int64)  # cell, ix, iy of each row
        self.row_z = np.empty(ncell)  # lowest point of each row
        self._point_bufs: dict[str, np.ndarray] = {}

    def next_sweep(self) -> int:
        self.sweep += 1
        return self.sweep

    def point_buf(self, name: str, n: int) -> np.ndarray:
        """A reusable int64 buffer of at least ``n`` entries (per-point rows and indices, which
        never leave one fusion call)."""
        buf = self._point_bufs.get(name)
        if buf is None or len(buf) < n:
            buf = self._point_bufs[name] = np.empty(max(n, 1024), dtype=np.int64)
        return buf[:n]

    def rows(self, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The distinct cells of ``flat`` (M,) sorted, and each entry's index among them."""
        self.mark[flat] = 1
        cells = np.flatnonzero(self.mark)
        self.mark[cells] = 0
        self.row[cells] = np.arange(len(cells))
        return cells, self.row[flat]


_SCRATCH: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _scratch(level: MapLevel) -> _Scratch:
    """The level's scratch (one set per level; fusing one level from two threads at once is
    not supported, as for every other write to a level)."""
    sc = _SCRATCH.get(level)
    if sc is None:
        sc = _SCRATCH[level] = _Scratch(level.size * level.size)
    return sc


def storage_flat(level: MapLevel, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    """Flat storage index (int64) of global cells ``ix, iy`` (N,) of ``level``."""
    size = level.size
    if size & (size - 1) == 0:  # a power of two: the modulo is a bit mask (also for negatives)
        return (iy & (size - 1)) * size + (ix & (size - 1))
    return (iy % size) * size + ix % size


def _ground_gate(
    level: MapLevel,
    sc: _Scratch,
    cells: np.ndarray,
    z_lo: np.ndarray,
    z_ref: float,
    config: FusionConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Height (relative to ``z_ref``) above which a point is an obstacle, one per cell with
    points this sweep (``cells`` (K,) flat indices, ``z_lo`` (K,) their lowest point); and the
    flat indices of cells whose estimate this sweep refutes.

    Reference: the estimate + 3 sigma where the cell has one; else ``min(own lowest point,
    lowest neighbour + slope allowance)`` over the 8 neighbours (their estimate if known, else
    their lowest point this sweep), so a cell whose every point lies on an object face is not
    taken for ground when a neighbour saw the ground. The gate adds ``obstacle_height_m``.
    A cell whose lowest point this sweep lies more than ``obstacle_height_m`` + 3 sigma below
    its estimate held an object's top (or something that has moved away): the hypothesis is
    denied (001, 4.5.3 hypothesize and test), and the cell starts again like a new one.
    """
    size = level.size
    elev = level.storage("elevation").reshape(-1)
    e = elev[cells].astype(np.float64) - z_ref
    sigma = np.sqrt(level.storage("elevation_var").reshape(-1)[cells].astype(np.float64))
    spread = 3.0 * np.nan_to_num(sigma)
    known = np.isfinite(e)
    stale = known & (z_lo < e - spread - config.obstacle_height_m)
    fresh = ~known | stale
    ref = np.where(fresh, z_lo, e + spread)
    new = cells[fresh]
    if new.size:
        sc.z_lo[cells] = z_lo  # dense, for the neighbours (put back to inf below)
        srow, scol = np.divmod(new, size)
        wrow = (srow - level.origin_cell[1]) % size  # window row/col: nothing across the seam
        wcol = (scol - level.origin_cell[0]) % size
        nb = np.full(new.shape, np.inf)
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if dr == 0 and dc == 0:
                    continue
                ok = (wrow + dr >= 0) & (wrow + dr < size) & (wcol + dc >= 0) & (wcol + dc < size)
                nflat = ((srow + dr) % size) * size + (scol + dc) % size
                en = elev[nflat]
                base = np.where(np.isnan(en), sc.z_lo[nflat], en.astype(np.float64) - z_ref)
                nb = np.where(ok, np.minimum(nb, base), nb)
        allowance = config.max_ground_slope * np.sqrt(2.0) * level.resolution_m
        ref[fresh] = np.minimum(z_lo[fresh], nb + allowance)
        sc.z_lo[cells] = np.inf
    return ref + config.obstacle_height_m, cells[stale]


def _child_flat(level: MapLevel, child: CellBatch) -> np.ndarray:
    """Flat storage index in ``level`` of each child cell's centre, -1 outside the window."""
    scale = child.resolution_m / level.resolution_m
    ix = np.floor((child.ix + 0.5) * scale).astype(np.int64) - level.origin_cell[0]
    iy = np.floor((child.iy + 0.5) * scale).astype(np.int64) - level.origin_cell[1]
    size = level.size
    ok = (ix >= 0) & (ix < size) & (iy >= 0) & (iy < size)
    flat = ((iy + level.origin_cell[1]) % size) * size + (ix + level.origin_cell[0]) % size
    return np.where(ok, flat, -1)


def apply(level: MapLevel, batch: CellBatch, config: FusionConfig, t_ns: int) -> int:
    """Update ``level``'s layers from ``batch`` (cells in its window); returns cells updated."""
    level.require(*FUSION_LAYERS)
    size = level.size
    col = batch.ix - level.origin_cell[0]
    row = batch.iy - level.origin_cell[1]
    ok = (col >= 0) & (col < size) & (row >= 0) & (row < size)
    if not ok.all():
        batch = _subset(batch, ok)
    cell = storage_flat(level, batch.ix, batch.iy)
    lay = {name: level.storage(name).reshape(-1) for name in FUSION_LAYERS}  # flat views

    g = batch.n > 0
    if batch.reset is not None and not batch.reset.any():
        batch = replace(batch, reset=None)  # nothing refuted: skip the refuted-cell passes
    if batch.reset is not None:  # refuted and no ground seen now: the cell's height is unknown
        gone = cell[batch.reset & ~g]
        for name in ("elevation", "elevation_var", "z_mean", "roughness"):
            lay[name][gone] = np.nan
        for name in ("z_weight", "z_sq_dev_sum", "count"):
            lay[name][gone] = 0
    if g.all():
        g = slice(None)  # every cell saw ground: views instead of masked copies
    gcell = cell[g]
    _kalman(lay, gcell, batch, g, config)
    _moments(lay, gcell, batch, g)

    lay["elevation_min"][cell] = np.fmin(lay["elevation_min"][cell], batch.z_min)
    lay["elevation_max"][cell] = np.fmax(lay["elevation_max"][cell], batch.z_max)
    lay["obstacle_count"][cell] += batch.n_obstacle.astype(np.int32)
    delta = np.where(batch.n_obstacle > 0, config.l_hit, config.l_miss)
    occ = lay["occupancy"][cell] + delta
    lay["occupancy"][cell] = np.clip(occ, config.l_min, config.l_max)
    lay["last_seen_ns"][cell] = int(t_ns)
    return len(batch)


def _kalman(
    lay: dict, gcell: np.ndarray, batch: CellBatch, g: np.ndarray | slice, config: FusionConfig
):
    """Scalar Kalman update of elevation / elevation_var in the cells with ground points."""
    R = 1.0 / batch.w[g]
    z_bar = batch.z_ref + batch.wz[g] * R
    x = lay["elevation"][gcell].astype(np.float64)
    P = lay["elevation_var"][gcell].astype(np.float64) + config.process_var_m2
    new = ~np.isfinite(x) | ~np.isfinite(P)  # first observation: the estimate is the measurement
    if batch.reset is not None:
        new |= batch.reset[g]
    P = np.where(new, 1.0, P)
    K = np.where(new, 1.0, P / (P + R))
    x = np.where(new, z_bar, x + K * (z_bar - x))
    P = np.where(new, R, (1.0 - K) * P)
    lay["elevation"][gcell] = x
    lay["elevation_var"][gcell] = P
    lay["confidence"][gcell] = config.confidence_var_m2 / (config.confidence_var_m2 + P)


def _moments(lay: dict, gcell: np.ndarray, batch: CellBatch, g: np.ndarray | slice) -> None:
    """Merge the sweep's weighted height moments into z_weight / z_mean / z_sq_dev_sum (W,
    mean and Welford's M2, by the weighted form of Chan et al.'s parallel update) ->
    roughness = sqrt(M2 / W); count += n."""
    w_b = batch.w[g]
    mean_b = batch.wz[g] / w_b
    m2_b = np.maximum(batch.wzz[g] - batch.wz[g] * mean_b, 0.0)
    mean_b = mean_b + batch.z_ref
    w_a, m2_a = lay["z_weight"][gcell], lay["z_sq_dev_sum"][gcell]
    if batch.reset is not None:
        keep = ~batch.reset[g]
        w_a, m2_a = np.where(keep, w_a, 0.0), np.where(keep, m2_a, 0.0)
        lay["count"][gcell] *= keep
    mean_a = np.where(w_a > 0, lay["z_mean"][gcell], mean_b)
    w = w_a + w_b
    delta = mean_b - mean_a
    m2 = m2_a + m2_b + delta * delta * w_a * w_b / w
    lay["z_weight"][gcell] = w
    lay["z_mean"][gcell] = mean_a + delta * w_b / w
    lay["z_sq_dev_sum"][gcell] = m2
    lay["roughness"][gcell] = np.sqrt(m2 / w)
    lay["count"][gcell] += batch.n[g].astype(np.int32)


def _subset(batch: CellBatch, keep: np.ndarray) -> CellBatch:
    arrays = {
        k: getattr(batch, k)[keep]
        for k in ("ix", "iy", "w", "wz", "wzz", "n", "n_obstacle", "z_min", "z_max")
    }
    arrays["reset"] = None if batch.reset is None else batch.reset[keep]
    return CellBatch(resolution_m=batch.resolution_m, z_ref=batch.z_ref, **arrays)


def fuse_points(
    level: MapLevel,
    points_xyz: np.ndarray,
    variance_m2: np.ndarray | float,
    t_ns: int,
    config: FusionConfig | None = None,
    ray_origin_xyz: np.ndarray | None = None,
) -> FusionStats:
    """Fuse world points ``(N, 3)`` with variances (m^2, scalar or (N,)) into one level.

    With ``ray_origin_xyz`` (the sensor's position in the world, metres (3,)), the cells the
    beams cross before their returns are lowered as free space too (:func:`cast_rays`).
    """
    config = config or FusionConfig()
    stats = FusionStats()
    if config.compiled:
        kp = kernel_points(points_xyz, variance_m2, config)
        stats.points_in = len(kp.xyz)
        batch, rest, n_drop, _ = summarise_compiled(level, kp, config)
        stats.dropped_nonfinite = n_drop
        stats.outside = len(rest)
        stats.cells_updated[level.name] = apply_compiled(level, batch, config, t_ns)
    else:
        pts = clean_points(points_xyz, variance_m2, stats)
        z_ref = float(pts.z.mean()) if len(pts) else 0.0
        batch = summarise(level, pts, config, z_ref)
        stats.outside = int(len(pts) - batch.n.sum() - batch.n_obstacle.sum())
        stats.cells_updated[level.name] = apply(level, batch, config, t_ns)
        mark_touched(level, batch)
    stats.ground[level.name] = int(batch.n.sum())
    stats.obstacle[level.name] = int(batch.n_obstacle.sum())
    if ray_origin_xyz is not None:
        xyz = np.ascontiguousarray(points_xyz, dtype=np.float64)
        stats.cells_freed[level.name] = cast_rays(level, xyz, ray_origin_xyz, config)
    return stats


# --- the compiled path (maps.kernels): the same results as summarise / apply above ----------


@dataclass(frozen=True)
class KernelPoints:
    """A sweep as the kernels read it: ``xyz`` (N, 3) float64 C-order world metres; ``var``
    float64 per point (N,) (``mode`` 0) or one scalar (1,) (mode 1), or, mode 2, none: each
    point's variance is ``(s0 + k r)^2`` from its range r (m) to ``origin`` (3,) world metres."""

    xyz: np.ndarray
    var: np.ndarray
    mode: int
    origin: np.ndarray
    s0: float
    k: float


_NO_ORIGIN = np.zeros(3)
_NO_INDEX = np.zeros(0, dtype=np.int64)


def kernel_points(
    points_xyz: np.ndarray,
    variance_m2: np.ndarray | float | None,
    config: FusionConfig,
    sensor_xyz: np.ndarray | None = None,
) -> KernelPoints:
    """Check shapes and wrap points for the kernels (no copy when already float64 C-order).
    ``variance_m2`` None takes range variance from ``sensor_xyz`` (:func:`range_variance`)."""
    pts = np.asarray(points_xyz)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FusionError(f"points_xyz must be (N, 3) world metres, got shape {pts.shape}")
    xyz = np.ascontiguousarray(pts, dtype=np.float64)
    n = len(xyz)
    s0, k = config.sigma0_m, config.sigma_per_m
    if variance_m2 is None:
        if sensor_xyz is None:
            raise FusionError("fuse needs variance_m2 or sensor_xyz (for range variance)")
        origin = np.asarray(sensor_xyz, dtype=np.float64).reshape(3)
        return KernelPoints(xyz, _NO_ORIGIN[:1], 2, origin, s0, k)
    var = np.asarray(variance_m2, dtype=np.float64)
    if var.ndim == 0:
        return KernelPoints(xyz, var.reshape(1), 1, _NO_ORIGIN, s0, k)
    if var.shape != (n,):
        raise FusionError(f"variance_m2 must be a scalar or ({n},), got shape {var.shape}")
    return KernelPoints(xyz, np.ascontiguousarray(var), 0, _NO_ORIGIN, s0, k)


def summarise_compiled(
    level: MapLevel,
    kp: KernelPoints,
    config: FusionConfig,
    idx: np.ndarray | None = None,
    z_ref: float | None = None,
    child: CellBatch | None = None,
) -> tuple[CellBatch, np.ndarray, int, float]:
    """:func:`summarise` by the kernels, in two passes over the points.

    ``idx`` None: every point of ``kp``, cleaned (non-finite or non-positive variance dropped),
    ``z_ref`` (if None) their mean height; else only the (clean) points ``idx`` (int64).
    Returns the batch, the indices (int64) of the kept points outside the window (a view of
    scratch memory, valid until this level's next call), the number dropped, and ``z_ref``.
    """
    sc = _scratch(level)
    sweep = sc.next_sweep()
    size, res = level.size, level.resolution_m
    ox, oy = (int(v) for v in level.origin_cell)
    use_idx = idx is not None
    n_iter = len(idx) if use_idx else len(kp.xyz)
    n_child = len(child) if child is not None else 0
    cells, cix, ciy = sc.row_ids  # rows of this sweep, copied out below
    z_lo = sc.row_z
    point_row, rest = sc.point_buf("row", n_iter), sc.point_buf("rest", n_iter)
    index = idx if use_idx else _NO_INDEX
    args = (kp.xyz, kp.var, kp.mode, kp.origin, kp.s0, kp.k, index, use_idx)
    m, n_rest, n_drop, z_sum = kernels.bin_points(
        *args, not use_idx, res, ox, oy, size, sc.tag, sweep,
        cells, cix, ciy, z_lo, point_row, rest,
    )  # fmt: skip
    if z_ref is None:
        n_kept = n_iter - n_drop
        z_ref = z_sum / n_kept if n_kept else 0.0
    cap = max(min(m + n_child, size * size), 1)
    w, wz, wzz, z_hi, gate = np.empty((5, cap))
    n, n_obs = np.empty((2, cap), dtype=np.int64)
    stale = np.zeros(cap, dtype=np.bool_)
    elev = level.storage("elevation").reshape(-1)
    elev_var = level.storage("elevation_var").reshape(-1)
    allowance = config.max_ground_slope * np.sqrt(2.0) * res
    kernels.ground_gate(
        m, cells, z_lo, z_ref, elev, elev_var, sc.z_lo, size, ox, oy,
        config.obstacle_height_m, allowance, gate, stale, _storage_order(sc, cells[:m]),
    )  # fmt: skip
    kernels.sum_points(*args, point_row, z_ref, gate, m, w, wz, wzz, n, n_obs, z_hi)
    if n_child:
        c = child
        m = kernels.merge_child(
            m, c.ix, c.iy, c.w, c.wz, c.wzz, c.n, c.n_obstacle, c.z_min, c.z_max, c.z_ref,
            c.resolution_m / res, z_ref, ox, oy, size, sc.tag, sweep,
            cells, cix, ciy, w, wz, wzz, n, n_obs, z_lo, z_hi,
        )  # fmt: skip
    batch = CellBatch(
        resolution_m=res,
        z_ref=z_ref,
        ix=cix[:m].copy(),
        iy=ciy[:m].copy(),
        w=w[:m],
        wz=wz[:m],
        wzz=wzz[:m],
        n=n[:m],
        n_obstacle=n_obs[:m],
        z_min=z_lo[:m] + z_ref,
        z_max=z_hi[:m] + z_ref,
        reset=stale[:m],
        flat=cells[:m].copy(),
    )
    return batch, rest[:n_rest], n_drop, z_ref


def apply_compiled(level: MapLevel, batch: CellBatch, config: FusionConfig, t_ns: int) -> int:
    """:func:`apply` by one kernel pass over the batch's cells; returns cells updated."""
    level.require(*FUSION_LAYERS)
    if batch.flat is None:  # a batch from elsewhere: keep the cells in the window
        col = batch.ix - level.origin_cell[0]
        row = batch.iy - level.origin_cell[1]
        ok = (col >= 0) & (col < level.size) & (row >= 0) & (row < level.size)
        batch = replace(_subset(batch, ok), flat=None)
        flat = storage_flat(level, batch.ix, batch.iy)
    else:
        flat = batch.flat
    reset = batch.reset if batch.reset is not None else np.zeros(len(batch), dtype=np.bool_)
    lay = [level.storage(name).reshape(-1) for name in FUSION_LAYERS]
    kernels.apply_cells(
        flat, batch.w, batch.wz, batch.wzz, batch.n, batch.n_obstacle, batch.z_min,
        batch.z_max, reset, batch.z_ref, int(t_ns), config.process_var_m2, config.l_hit,
        config.l_miss, config.l_min, config.l_max, config.confidence_var_m2, *lay,
        _storage_order(_scratch(level), flat),
    )  # fmt: skip
    return len(batch)


_IN_ORDER = np.zeros(0, dtype=np.int64)


def _storage_order(sc: _Scratch, flat: np.ndarray) -> np.ndarray:
    """Rows of ``flat`` (distinct storage indices) by storage index, for the per-cell kernels;
    an empty array (row order) when the rows are too few to be worth ordering (a scan over the
    level's cells costs about as much as 2 000 scattered cells)."""
    if len(flat) * 32 < len(sc.order_mark):
        return _IN_ORDER
    order = np.empty(len(flat), dtype=np.int64)
    if kernels.storage_order(flat, sc.order_mark, order) != len(flat):
        return _IN_ORDER  # a cell given twice: keep the batch's order, as the reference does
    return order


def mark_touched(level: MapLevel, batch: CellBatch) -> None:
    """Start a sweep in the level's scratch with the batch's cells touched (what the compiled
    path does as it bins), so :func:`cast_rays` leaves them to their own hit / miss."""
    sc = _scratch(level)
    sc.tag[storage_flat(level, batch.ix, batch.iy)] = sc.next_sweep() << 32


def cast_rays(
    level: MapLevel,
    points_xyz: np.ndarray,
    origin_xyz: np.ndarray,
    config: FusionConfig,
) -> int:
    """Free-space update of one sweep already fused into ``level`` (call right after it).

    Each beam from ``origin_xyz`` (sensor position, world metres (3,)) to its point of
    ``points_xyz`` (N, 3) float64 world metres (every ``config.ray_stride``-th beam, and no more
    than ``config.ray_max_beams``) lowers the
    occupancy log-odds of the cells it crosses before its end cell by ``l_miss``, once per
    sweep, up to ``ray_max_range_m`` (horizontal) and only where it passes at most
    ``ray_free_height_m`` above the cell's ground (its elevation, else the beam end's height)
    and not above the highest point ever seen there (a beam over an object's top is not
    through it; below it, the object has gone).
    Cells holding points this sweep keep their own update (an obstacle point's hit wins), so
    a cell changes once per sweep: the inverse sensor model of an occupancy grid
    (001, 4.4.7: "which regions are visible from a particular viewpoint"). Returns the cells
    lowered. NaN/inf points are skipped.
    """
    origin = np.asarray(origin_xyz, dtype=np.float64).reshape(-1)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise FusionError(f"ray_origin_xyz must be a finite world (x, y, z), got {origin_xyz!r}")
    level.require("elevation", "elevation_max", "occupancy")
    xyz = np.ascontiguousarray(points_xyz, dtype=np.float64)
    stride = int(config.ray_stride)
    if stride < 1:
        raise FusionError(f"ray_stride must be >= 1, got {config.ray_stride!r}")
    cap = config.ray_max_beams
    if cap is not None:
        if cap < 1:
            raise FusionError(f"ray_max_beams must be >= 1 or None, got {cap!r}")
        stride = max(stride, -(-len(points_xyz) // cap))
    idx = np.arange(0, len(xyz), stride, dtype=np.int64) if stride > 1 else _NO_INDEX
    sc = _scratch(level)
    ox, oy = (int(v) for v in level.origin_cell)
    return int(
        kernels.cast_rays(
            xyz, idx, stride > 1, origin, level.resolution_m, ox, oy, level.size,
            float(config.ray_max_range_m), float(config.ray_free_height_m),
            int(config.ray_stop_after_cells), sc.tag, sc.sweep,
            sc.ray_stamp, sc.start_stamp, sc.start_beam, level.storage("elevation").reshape(-1),
            level.storage("elevation_max").reshape(-1), level.storage("occupancy").reshape(-1),
            float(config.l_miss), float(config.l_min),
        )
    )  # fmt: skip


def fuse_labels(
    level: MapLevel,
    points_xyz: np.ndarray,
    entity_id: np.ndarray,
    class_id: np.ndarray | None = None,
) -> int:
    """Write SP labels at world points ``(N, 3)``: ``entity_id`` (N,) int, ``class_id`` (N,).

    Negative ids mean "no label" and are skipped; where several points hit one cell, the last
    one wins. Returns how many points were written.
    """
    pts = np.asarray(points_xyz, dtype=np.float64)
    ent = np.asarray(entity_id)
    if pts.ndim != 2 or pts.shape[1] != 3 or ent.shape != pts.shape[:1]:
        raise FusionError(
            f"labels need points (N, 3) and entity_id (N,), got {pts.shape} and {ent.shape}"
        )
    if class_id is not None and np.shape(class_id) != ent.shape:
        raise FusionError(f"class_id shape {np.shape(class_id)} differs from {ent.shape}")
    keep = np.isfinite(pts).all(axis=1) & (ent >= 0)
    # the points' cells once for both layers (MapLevel.write's own steps)
    rows, cols, inside = level.world_to_window(pts[keep, :2])
    srow, scol = level.window_to_storage(rows[inside], cols[inside])
    layer = level.storage("entity_id")
    layer[srow, scol] = ent[keep][inside].astype(layer.dtype, copy=False)
    if class_id is not None:
        layer = level.storage("class_id")
        layer[srow, scol] = np.asarray(class_id)[keep][inside].astype(layer.dtype, copy=False)
    return int(np.count_nonzero(inside))


def labels_from_entity_image(
    entity_image: np.ndarray, class_image: np.ndarray | None, xyz_world_image: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Flatten an SP entity image (H, W) int, optional class image (H, W) int and the world
    points of its pixels (H, W, 3) (from the range image) into :func:`fuse_labels` inputs,
    keeping pixels with a finite point and an id >= 0."""
    ent = np.asarray(entity_image)
    xyz = np.asarray(xyz_world_image, dtype=np.float64)
    if xyz.shape != (*ent.shape, 3):
        raise FusionError(
            f"xyz image must be {(*ent.shape, 3)} for entity image {ent.shape}, got {xyz.shape}"
        )
    keep = (ent >= 0) & np.isfinite(xyz).all(axis=-1)
    cls = None if class_image is None else np.asarray(class_image)[keep]
    return xyz[keep], ent[keep], cls
