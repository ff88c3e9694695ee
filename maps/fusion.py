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
point this sweep lowers its log-odds (no ray casting: cells the beams pass over are not
updated).

Everything is vectorised with ``np.bincount`` / ``np.minimum.at`` over flat cell indices; the
per-sweep sufficient statistics of a level (:class:`CellBatch`) are additive, so a finer level
hands them to the next coarser one (see :mod:`maps.stack`) and no point is counted twice.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from maps.level import MapLevel

FUSION_LAYERS = (
    "elevation",
    "elevation_var",
    "elevation_min",
    "elevation_max",
    "count",
    "obstacle_count",
    "z_mean",
    "z_m2",
    "roughness",
    "occupancy",
    "confidence",
    "last_seen_ns",
)


class FusionError(ValueError):
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


def range_variance(ranges_m: np.ndarray, config: FusionConfig) -> np.ndarray:
    """Per-point height variance (m^2, float64) from range (m): ``(sigma0 + k r)^2``."""
    r = np.asarray(ranges_m, dtype=np.float64)
    return (config.sigma0_m + config.sigma_per_m * r) ** 2


@dataclass
class CellBatch:
    """One sweep's sufficient statistics per touched cell of one level (all arrays (M,)).

    ``ix, iy`` global cell indices (int64) of the level that made the batch, at
    ``resolution_m``; ground points give ``w = sum 1/var``, ``wz = sum (z - z_ref)/var``,
    ``n``, ``s1 = sum (z - z_ref)``, ``s2 = sum (z - z_ref)^2``; all points give
    ``z_min, z_max``; obstacle points ``n_obstacle``. ``z_ref`` (m) is one scalar per sweep.
    """

    resolution_m: float
    z_ref: float
    ix: np.ndarray
    iy: np.ndarray
    w: np.ndarray
    wz: np.ndarray
    n: np.ndarray
    s1: np.ndarray
    s2: np.ndarray
    z_min: np.ndarray
    z_max: np.ndarray
    n_obstacle: np.ndarray

    def __len__(self) -> int:
        return int(self.ix.shape[0])


@dataclass
class FusionStats:
    """What one fusion call did, per level name and in total."""

    points_in: int = 0
    dropped_nonfinite: int = 0
    outside: int = 0
    ground: dict[str, int] = field(default_factory=dict)
    obstacle: dict[str, int] = field(default_factory=dict)
    cells_updated: dict[str, int] = field(default_factory=dict)


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
    cols = PointColumns(
        *(np.ascontiguousarray(pts[:, k], dtype=np.float64) for k in range(3)),
        np.ascontiguousarray(np.broadcast_to(var, (n,))),
    )
    stats.points_in += n
    ok = np.isfinite(cols.x + cols.y + cols.z + cols.var) & (cols.var > 0)  # nan/inf propagate
    if not ok.all():
        stats.dropped_nonfinite += n - int(np.count_nonzero(ok))
        cols = cols.subset(ok)
    return cols


def summarise(
    level: MapLevel,
    points: PointColumns,
    config: FusionConfig,
    z_ref: float,
    child: CellBatch | None = None,
) -> CellBatch:
    """Per-cell statistics of ``points`` (those inside the window) plus a finer level's batch.

    Points must be finite; points outside the window are ignored. The child batch's cells are
    attributed to the cell holding their centre (exact when resolutions nest by an integer
    ratio).
    """
    size = level.size
    res = level.resolution_m
    ix = np.floor(points.x / res).astype(np.int64)
    iy = np.floor(points.y / res).astype(np.int64)
    inside = ((ix - level.origin_cell[0]).view(np.uint64) < size) & (
        (iy - level.origin_cell[1]).view(np.uint64) < size
    )  # negative offsets wrap to huge unsigned values
    z, var = points.z, points.var
    if not inside.all():
        ix, iy, z, var = ix[inside], iy[inside], z[inside], var[inside]
    flat = storage_flat(level, ix, iy)
    z = z - z_ref
    ncell = size * size

    # ground reference: the current estimate (+3 sigma), else the lowest point of this sweep
    # in the cell or, lower still, in a neighbouring cell (+ a slope allowance)
    z_lo = np.full(ncell, np.inf)
    np.minimum.at(z_lo, flat, z)
    elev_l = level.storage("elevation").reshape(-1)
    elev = elev_l[flat].astype(np.float64) - z_ref
    known = np.isfinite(elev)
    ref = _new_cell_reference(level, z_lo, z_ref, config)[flat]
    if known.any():
        sigma = np.sqrt(level.storage("elevation_var").reshape(-1)[flat].astype(np.float64))
        ref = np.where(known, elev + 3.0 * np.nan_to_num(sigma), ref)
    ground = z <= ref + config.obstacle_height_m
    w = np.where(ground, 1.0 / var, 0.0)
    g = ground.astype(np.float64)

    idx, parts = flat, [w, w * z, g, g * z, g * z * z, 1.0 - g]
    z_all = z
    if child is not None and len(child):
        cflat = _child_flat(level, child)
        ok = cflat >= 0
        cflat = cflat[ok]
        idx = np.concatenate([flat, cflat])
        cz = child.z_ref - z_ref
        cn = child.n[ok].astype(np.float64)
        cs1 = child.s1[ok] + cn * cz
        cs2 = child.s2[ok] + 2.0 * cz * child.s1[ok] + cn * cz * cz
        cw = child.w[ok]
        extra = [cw, child.wz[ok] + cw * cz, cn, cs1, cs2, child.n_obstacle[ok].astype(np.float64)]
        parts = [np.concatenate([a, b]) for a, b in zip(parts, extra, strict=True)]
        z_lo_child, z_hi_child = child.z_min[ok] - z_ref, child.z_max[ok] - z_ref
        np.minimum.at(z_lo, cflat, z_lo_child)
        z_all = np.concatenate([z, z_hi_child])
    sums = [np.bincount(idx, weights=p, minlength=ncell) for p in parts]
    z_hi = np.full(ncell, -np.inf)
    np.maximum.at(z_hi, idx, z_all)

    n_all = sums[2] + sums[5]
    cells = np.flatnonzero(n_all > 0)
    s_row, s_col = np.divmod(cells, size)
    ix = level.origin_cell[0] + (s_col - level.origin_cell[0]) % size
    iy = level.origin_cell[1] + (s_row - level.origin_cell[1]) % size
    return CellBatch(
        resolution_m=level.resolution_m,
        z_ref=z_ref,
        ix=ix,
        iy=iy,
        w=sums[0][cells],
        wz=sums[1][cells],
        n=np.rint(sums[2][cells]).astype(np.int64),
        s1=sums[3][cells],
        s2=sums[4][cells],
        z_min=z_lo[cells] + z_ref,
        z_max=z_hi[cells] + z_ref,
        n_obstacle=np.rint(sums[5][cells]).astype(np.int64),
    )


def storage_flat(level: MapLevel, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    """Flat storage index (int64) of global cells ``ix, iy`` (N,) of ``level``."""
    size = level.size
    if size & (size - 1) == 0:  # a power of two: the modulo is a bit mask (also for negatives)
        return (iy & (size - 1)) * size + (ix & (size - 1))
    return (iy % size) * size + ix % size


def _new_cell_reference(
    level: MapLevel, z_lo: np.ndarray, z_ref: float, config: FusionConfig
) -> np.ndarray:
    """Dense (size*size,) ground reference for cells with points this sweep and no estimate:
    ``min(own lowest point, lowest neighbour + slope allowance)`` over the 8 neighbours
    (their estimate if known, else their lowest point this sweep). A cell whose every point
    lies on an object face is then not mistaken for ground when a neighbour saw the ground."""
    size = level.size
    elev = level.storage("elevation").reshape(-1)
    cells = np.flatnonzero(np.isfinite(z_lo) & np.isnan(elev))
    ref = z_lo.copy()
    if cells.size == 0:
        return ref
    base = np.where(np.isnan(elev), z_lo, elev.astype(np.float64) - z_ref)
    srow, scol = np.divmod(cells, size)
    wrow = (srow - level.origin_cell[1]) % size  # window row/col: no neighbours across the seam
    wcol = (scol - level.origin_cell[0]) % size
    nb = np.full(cells.shape, np.inf)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr == 0 and dc == 0:
                continue
            ok = (wrow + dr >= 0) & (wrow + dr < size) & (wcol + dc >= 0) & (wcol + dc < size)
            nflat = ((srow + dr) % size) * size + (scol + dc) % size
            nb = np.where(ok, np.minimum(nb, base[nflat]), nb)
    allowance = config.max_ground_slope * np.sqrt(2.0) * level.resolution_m
    ref[cells] = np.minimum(z_lo[cells], nb + allowance)
    return ref


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
        col, row = col[ok], row[ok]
    srow, scol = (row + level.origin_cell[1]) % size, (col + level.origin_cell[0]) % size
    cell = (srow, scol)
    lay = {name: level.storage(name) for name in FUSION_LAYERS}

    g = batch.n > 0
    gcell = (srow[g], scol[g])
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


def _kalman(lay: dict, gcell: tuple, batch: CellBatch, g: np.ndarray, config: FusionConfig):
    """Scalar Kalman update of elevation / elevation_var in the cells with ground points."""
    R = 1.0 / batch.w[g]
    z_bar = batch.z_ref + batch.wz[g] * R
    x = lay["elevation"][gcell].astype(np.float64)
    P = lay["elevation_var"][gcell].astype(np.float64) + config.process_var_m2
    new = ~np.isfinite(x) | ~np.isfinite(P)  # first observation: the estimate is the measurement
    P = np.where(new, 1.0, P)
    K = np.where(new, 1.0, P / (P + R))
    x = np.where(new, z_bar, x + K * (z_bar - x))
    P = np.where(new, R, (1.0 - K) * P)
    lay["elevation"][gcell] = x
    lay["elevation_var"][gcell] = P
    lay["confidence"][gcell] = config.confidence_var_m2 / (config.confidence_var_m2 + P)


def _moments(lay: dict, gcell: tuple, batch: CellBatch, g: np.ndarray) -> None:
    """Merge the sweep's height moments into count / z_mean / z_m2 (Chan et al.) -> roughness."""
    n_b = batch.n[g].astype(np.float64)
    mean_b = batch.s1[g] / n_b
    m2_b = np.maximum(batch.s2[g] - batch.s1[g] * mean_b, 0.0)
    mean_b = mean_b + batch.z_ref
    n_a = lay["count"][gcell].astype(np.float64)
    mean_a = np.where(n_a > 0, lay["z_mean"][gcell], mean_b)
    m2_a = lay["z_m2"][gcell]
    n = n_a + n_b
    delta = mean_b - mean_a
    mean = mean_a + delta * n_b / n
    m2 = m2_a + m2_b + delta * delta * n_a * n_b / n
    lay["count"][gcell] = n.astype(np.int32)
    lay["z_mean"][gcell] = mean
    lay["z_m2"][gcell] = m2
    lay["roughness"][gcell] = np.sqrt(m2 / n)


def _subset(batch: CellBatch, keep: np.ndarray) -> CellBatch:
    arrays = {
        k: getattr(batch, k)[keep]
        for k in ("ix", "iy", "w", "wz", "n", "s1", "s2", "z_min", "z_max", "n_obstacle")
    }
    return CellBatch(resolution_m=batch.resolution_m, z_ref=batch.z_ref, **arrays)


def fuse_points(
    level: MapLevel,
    points_xyz: np.ndarray,
    variance_m2: np.ndarray | float,
    t_ns: int,
    config: FusionConfig | None = None,
) -> FusionStats:
    """Fuse world points ``(N, 3)`` with variances (m^2, scalar or (N,)) into one level."""
    config = config or FusionConfig()
    stats = FusionStats()
    pts = clean_points(points_xyz, variance_m2, stats)
    z_ref = float(pts.z.mean()) if len(pts) else 0.0
    batch = summarise(level, pts, config, z_ref)
    stats.outside = int(len(pts) - batch.n.sum() - batch.n_obstacle.sum())
    stats.ground[level.name] = int(batch.n.sum())
    stats.obstacle[level.name] = int(batch.n_obstacle.sum())
    stats.cells_updated[level.name] = apply(level, batch, config, t_ns)
    return stats


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
    level.write("entity_id", pts[keep], ent[keep])
    if class_id is not None:
        level.write("class_id", pts[keep], np.asarray(class_id)[keep])
    return int(np.count_nonzero(keep & level.contains(pts)))


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
