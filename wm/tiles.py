"""Map tiles in the knowledge database: the maps' tile store backed by the KD's long-term memory.

Reference 001, 4.4.11 (line 782: long-term memory contains maps; 784: local maps update the
stored ones). Cells leaving a level's window go to the KD and come back when the vehicle
returns, also in a later run over the same KD file (DESIGN.md section 5, memory tiers).
This is the adapter at the edge: maps knows only its two-method
:class:`~maps.tiles.TileStore`, kd_store only named arrays under ``(level, tx, ty)``.

The window a run starts or ends with never leaves it, so :func:`map_stack_over_kd` fills a new
stack's first windows from the KD, and :func:`keep_windows` puts the last windows in at the end.
"""

from __future__ import annotations

import numpy as np

import kd_store
from maps.level import MapLevel
from maps.stack import MapStack, StackConfig
from maps.tiles import Tile, TileKey


class KDTileStore:
    """:class:`~maps.tiles.TileStore` over a KD: ``put`` and ``get`` copy the arrays."""

    def __init__(self, kd: kd_store.KnowledgeDatabase) -> None:
        self.kd = kd

    def put(self, key: TileKey, tile: Tile) -> None:
        level, tx, ty = key
        self.kd.put_tile(level, tx, ty, tile)

    def get(self, key: TileKey) -> Tile | None:
        level, tx, ty = key
        return self.kd.get_tile(level, tx, ty)


def map_stack_over_kd(
    kd: kd_store.KnowledgeDatabase, config: StackConfig | None = None
) -> MapStack:
    """A map stack whose tiles live in ``kd``, its first windows filled from the tiles there."""
    stack = MapStack(config, store=KDTileStore(kd))
    for lvl in stack.levels:
        load_window(lvl)
    return stack


def keep_windows(stack: MapStack) -> int:
    """Put every level's current window into its tile store (at the end of a run); returns
    the tiles put."""
    return sum(save_window(lvl) for lvl in stack.levels)


def _tiles_of_window(lvl: MapLevel):
    """Yield ``(tx, ty, window slices, tile slices)`` for every tile meeting the window."""
    t = lvl.config.tile_cells
    ix0, iy0 = (int(v) for v in lvl.origin_cell)
    for ty in range(iy0 // t, (iy0 + lvl.size - 1) // t + 1):
        y_lo, y_hi = max(iy0, ty * t), min(iy0 + lvl.size, (ty + 1) * t)
        for tx in range(ix0 // t, (ix0 + lvl.size - 1) // t + 1):
            x_lo, x_hi = max(ix0, tx * t), min(ix0 + lvl.size, (tx + 1) * t)
            win = (slice(y_lo - iy0, y_hi - iy0), slice(x_lo - ix0, x_hi - ix0))
            tile = (slice(y_lo - ty * t, y_hi - ty * t), slice(x_lo - tx * t, x_hi - tx * t))
            yield tx, ty, win, tile


def load_window(lvl: MapLevel) -> int:
    """Fill ``lvl``'s window from the tiles its store holds (tiles are ``[row, col]`` =
    ``[iy - ty * tile_cells, ix - tx * tile_cells]``, as maps.level writes them); returns
    the tiles read. Cells without a stored tile keep their values."""
    if lvl.store is None:
        return 0
    windows = {name: lvl.window(name) for name in lvl.layer_names}
    n = 0
    for tx, ty, win, part in _tiles_of_window(lvl):
        tile = lvl.store.get((lvl.name, tx, ty))
        if tile is None:
            continue
        n += 1
        for name, w in windows.items():
            if name in tile:
                w[win] = tile[name][part]
    if n:
        for name, w in windows.items():
            lvl.set_window(name, w)
    return n


def save_window(lvl: MapLevel) -> int:
    """Put ``lvl``'s window into its store, merged into the tiles already there (cells of a
    tile outside the window keep their stored values); returns the tiles put. Tiles that are
    empty (every layer at its fill) and not stored yet are skipped."""
    if lvl.store is None:
        return 0
    t = lvl.config.tile_cells
    windows = {name: lvl.window(name) for name in lvl.layer_names}
    n = 0
    for tx, ty, win, part in _tiles_of_window(lvl):
        key = (lvl.name, tx, ty)
        tile = lvl.store.get(key)
        blocks = {name: w[win] for name, w in windows.items()}
        if tile is None:
            if all(_is_fill(b, lvl.specs[name].fill) for name, b in blocks.items()):
                continue
            tile = {name: spec.empty((t, t)) for name, spec in lvl.specs.items()}
        for name, b in blocks.items():
            if name not in tile:  # a layer the stored tile was written without
                tile[name] = lvl.specs[name].empty((t, t))
            tile[name][part] = b
        lvl.store.put(key, tile)
        n += 1
    return n


def _is_fill(block: np.ndarray, fill: float | int) -> bool:
    if isinstance(fill, float) and np.isnan(fill):
        return bool(np.isnan(block).all())
    return bool((block == fill).all())
