"""The map stack: levels 2-5 of the reference model scrolling together around the vehicle.

Default levels (reference 000, Table 2; docs/architecture.md, map levels and tiles): primitive
0.04 m, subsystem 0.4 m, vehicle 4 m, section 30 m, each 256 x 256 cells centred on the
vehicle. "At each level, maps have more resolution but less range than at the level above"
(001, 4.4.7).

Fusion: every point is fused raw into the finest level whose window holds it; that level's
per-cell sweep statistics (:class:`~maps.fusion.CellBatch`) are then handed to the next
coarser level together with the raw points that only it holds, and so on up. So every level
sees every point in its window exactly once, and the coarse levels never re-bin raw points
the fine levels already summarised. Given the sensor position, the ``raycast_levels``
(default the 0.4 m level) also trace free space along the beams. A priori terrain (an
:class:`~maps.apriori.ElevationRaster`) feeds the coarse levels and refills their cells as
they scroll in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from core.errors import EngineError
from maps.apriori import ElevationRaster, write_raster
from maps.fusion import (
    FusionConfig,
    FusionError,
    FusionStats,
    apply,
    apply_compiled,
    cast_rays,
    clean_points,
    fuse_labels,
    kernel_points,
    mark_touched,
    range_variance,
    summarise,
    summarise_compiled,
    window_cells,
)
from maps.level import LevelConfig, MapLevel
from maps.terrain import TerrainConfig, update_terrain
from maps.tiles import InMemoryTileStore, TileStore


class StackError(EngineError, ValueError):
    """A stack configuration or call the stack cannot take (names the value)."""


DEFAULT_LEVELS: tuple[LevelConfig, ...] = (
    LevelConfig("primitive", 0.04, keep_tiles=False),  # level 2: seconds of memory only
    LevelConfig("subsystem", 0.4),  # level 3
    LevelConfig("vehicle", 4.0),  # level 4
    LevelConfig("section", 30.0),  # level 5
)


@dataclass(frozen=True)
class StackConfig:
    """Levels (finest first), fusion and terrain settings, and how a priori terrain enters."""

    levels: tuple[LevelConfig, ...] = DEFAULT_LEVELS
    fusion: FusionConfig = field(default_factory=FusionConfig)
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    apriori_min_resolution_m: float = 4.0  # levels at least this coarse take a priori terrain
    apriori_var_m2: float = 0.25  # variance given to a priori heights
    raycast_levels: tuple[str, ...] = ("subsystem",)  # levels that trace free space (rays)


class MapStack:
    """All map levels, moved together, fed with world points, backed by one tile store."""

    def __init__(self, config: StackConfig | None = None, store: TileStore | None = None):
        self.config = config or StackConfig()
        cfgs = self.config.levels
        if not cfgs:
            raise StackError("a map stack needs at least one level")
        names = [c.name for c in cfgs]
        if len(set(names)) != len(names):
            raise StackError(f"level names must be unique, got {names}")
        res = [c.resolution_m for c in cfgs]
        if any(not (isinstance(r, int | float) and r > 0) for r in res) or res != sorted(res):
            raise StackError(f"level resolutions must be > 0 and increasing (finest first): {res}")
        self.store = store if store is not None else InMemoryTileStore()
        self.levels = [MapLevel(c, self.store) for c in cfgs]
        self.raster: ElevationRaster | None = None
        self.T_world_body: np.ndarray | None = None
        self.t_last_fused_ns: int = -1  # time (int64 ns) of the last fused sweep; -1: none yet

    def keep_windows(self) -> int:
        """Put every level's current window into the tile store (at the end of a run, so a
        later stack over the same store starts from it); returns the tiles put."""
        return sum(lvl.keep_window() for lvl in self.levels)

    def level(self, name: str) -> MapLevel:
        """The level called ``name``."""
        for lvl in self.levels:
            if lvl.name == name:
                return lvl
        raise StackError(f"no level {name!r}; levels: {[lvl.name for lvl in self.levels]}")

    # --- moving ----------------------------------------------------------------------------

    def move_to_pose(self, T_world_body: np.ndarray) -> None:
        """Centre every level on the body position of pose ``T_world_body`` (4x4)."""
        T = np.asarray(T_world_body, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise StackError(f"T_world_body must be a finite 4x4 pose, got shape {T.shape}")
        self.T_world_body = T
        self.move_to(T[:2, 3])

    def move_to(self, center_xy: np.ndarray) -> None:
        """Centre every level on world point ``center_xy`` (metres); refill a priori cells."""
        for lvl in self.levels:
            dx, dy = lvl.move_to(center_xy)
            if (dx or dy) and self._takes_apriori(lvl):
                rows, cols = entering_cells(dx, dy, lvl.size)
                write_raster(lvl, self.raster, self.config.apriori_var_m2, rows, cols)

    # --- a priori terrain ------------------------------------------------------------------

    def set_apriori(self, raster: ElevationRaster) -> dict[str, int]:
        """Use ``raster`` as a priori terrain for the coarse levels; fills their empty cells now
        and as they scroll. Returns cells written per level."""
        self.raster = raster
        return {
            lvl.name: write_raster(lvl, raster, self.config.apriori_var_m2)
            for lvl in self.levels
            if self._takes_apriori(lvl)
        }

    def _takes_apriori(self, lvl: MapLevel) -> bool:
        return self.raster is not None and lvl.resolution_m >= self.config.apriori_min_resolution_m

    # --- fusion ----------------------------------------------------------------------------

    def fuse(
        self,
        points_world: np.ndarray,
        *,
        t_ns: int,
        variance_m2: np.ndarray | float | None = None,
        sensor_xyz: np.ndarray | None = None,
        ray_origin_xyz: np.ndarray | None = None,
    ) -> FusionStats:
        """Fuse world points ``(N, 3)`` metres into every level (see the module docstring).

        Give either per-point ``variance_m2`` (m^2) or the sensor position ``sensor_xyz`` in
        the world (range-dependent variance, :func:`~maps.fusion.range_variance`). Non-finite
        points are dropped and counted in the returned stats. With ``ray_origin_xyz`` (the
        sensor position in the world, metres), the ``raycast_levels`` also lower the cells
        the beams cross (:func:`~maps.fusion.cast_rays`).
        """
        fcfg = self.config.fusion
        if fcfg.compiled:
            stats = self._fuse_compiled(points_world, t_ns, variance_m2, sensor_xyz)
        else:
            stats = self._fuse_numpy(points_world, t_ns, variance_m2, sensor_xyz)
        self.t_last_fused_ns = int(t_ns)
        if ray_origin_xyz is not None:
            names = [lvl.name for lvl in self.levels]
            unknown = sorted(set(self.config.raycast_levels) - set(names))
            if unknown:
                raise StackError(f"raycast_levels {unknown} are not among the levels {names}")
            xyz = np.ascontiguousarray(points_world, dtype=np.float64)
            for lvl in self.levels:
                if lvl.name in self.config.raycast_levels:
                    stats.cells_freed[lvl.name] = cast_rays(lvl, xyz, ray_origin_xyz, fcfg)
        return stats

    def _fuse_compiled(self, points_world, t_ns, variance_m2, sensor_xyz) -> FusionStats:
        """The kernel path: two passes over each level's points, one over its cells."""
        fcfg = self.config.fusion
        kp = kernel_points(points_world, variance_m2, fcfg, sensor_xyz)
        stats = FusionStats(points_in=len(kp.xyz))
        idx, z_ref, child = None, None, None
        for lvl in self.levels:  # finest first: each point goes raw to the finest level holding it
            batch, idx, n_drop, z_ref = summarise_compiled(lvl, kp, fcfg, idx, z_ref, child)
            if lvl is self.levels[0]:
                stats.dropped_nonfinite = n_drop
            stats.cells_updated[lvl.name] = apply_compiled(lvl, batch, fcfg, t_ns)
            stats.ground[lvl.name] = int(batch.n.sum())
            stats.obstacle[lvl.name] = int(batch.n_obstacle.sum())
            child = batch
        stats.outside = len(idx)
        return stats

    def _fuse_numpy(self, points_world, t_ns, variance_m2, sensor_xyz) -> FusionStats:
        """The numpy reference path (``FusionConfig(compiled=False)``)."""
        pts = np.asarray(points_world)
        if variance_m2 is None:
            if sensor_xyz is None:
                raise FusionError("fuse needs variance_m2 or sensor_xyz (for range variance)")
            if pts.ndim != 2 or pts.shape[1] != 3:
                raise FusionError(f"points_world must be (N, 3) metres, got shape {pts.shape}")
            origin = np.asarray(sensor_xyz, dtype=np.float64).reshape(3)
            variance_m2 = range_variance(np.linalg.norm(pts - origin, axis=1), self.config.fusion)
        stats = FusionStats()
        pts = clean_points(pts, variance_m2, stats)
        z_ref = float(pts.z.mean()) if len(pts) else 0.0
        child = None
        for lvl in self.levels:  # finest first: each point goes raw to the finest level holding it
            ix, iy, mine = window_cells(lvl, pts)
            cells = (ix[mine], iy[mine])
            batch = summarise(lvl, pts.subset(mine), self.config.fusion, z_ref, child, cells)
            pts = pts.subset(~mine)
            stats.cells_updated[lvl.name] = apply(lvl, batch, self.config.fusion, t_ns)
            stats.ground[lvl.name] = int(batch.n.sum())
            stats.obstacle[lvl.name] = int(batch.n_obstacle.sum())
            mark_touched(lvl, batch)
            child = batch
        stats.outside = len(pts)
        return stats

    def fuse_labels(
        self, points_world: np.ndarray, entity_id: np.ndarray, class_id: np.ndarray | None = None
    ) -> dict[str, int]:
        """Write SP labels (see :func:`~maps.fusion.fuse_labels`) into every level whose window
        holds the points; returns points written per level."""
        pts, ent, cls = np.asarray(points_world), np.asarray(entity_id), class_id
        same = cls is None or np.shape(cls) == ent.shape
        if pts.ndim == 2 and ent.shape == pts.shape[:1] and same:
            # only labelled points write anything: select them once, not once per level
            sel = np.flatnonzero(ent >= 0)
            pts, ent = pts[sel].astype(np.float64), ent[sel]
            cls = None if cls is None else np.asarray(cls)[sel]
        return {lvl.name: fuse_labels(lvl, pts, ent, cls) for lvl in self.levels}

    def update_terrain(self) -> None:
        """Recompute slope, step height and traversability on every level."""
        for lvl in self.levels:
            update_terrain(lvl, self.config.terrain)


def entering_cells(dx: int, dy: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Window ``(rows, cols)`` of the cells that entered on a move of ``(dx, dy)`` cells."""
    mask = np.zeros((size, size), dtype=bool)
    if abs(dx) >= size or abs(dy) >= size:
        mask[:] = True
    else:
        if dx > 0:
            mask[:, size - dx :] = True
        elif dx < 0:
            mask[:, :-dx] = True
        if dy > 0:
            mask[size - dy :, :] = True
        elif dy < 0:
            mask[:-dy, :] = True
    rows, cols = np.nonzero(mask)
    return rows, cols
