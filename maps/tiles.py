"""Long-term memory of map tiles: cells that leave a level's window are kept and come back.

A tile is a square block of ``tile_cells x tile_cells`` cells of one level, all layers, keyed
by ``(level name, tile x index, tile y index)`` in the level's fixed world grid (reference 001,
4.4.11: long-term memory holds maps; local maps update the stored ones).
:class:`InMemoryTileStore` keeps tiles in a dict; the knowledge database's long-term memory
stands behind the same two-method :class:`TileStore` interface through the adapter
``wm.tiles.KDTileStore`` (maps does not import the KD). A level fills its first window from
its store, and ``MapLevel.keep_window`` puts the current window in.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

TileKey = tuple[str, int, int]
Tile = dict[str, np.ndarray]  # layer name -> (tile_cells, tile_cells) array, window order


class TileStore(Protocol):
    """Where tiles go when they leave a window: ``put`` replaces, ``get`` returns None if absent."""

    def put(self, key: TileKey, tile: Tile) -> None: ...

    def get(self, key: TileKey) -> Tile | None: ...


class InMemoryTileStore:
    """Tiles in a dict (process lifetime). Arrays are stored as given; callers pass copies."""

    def __init__(self) -> None:
        self._tiles: dict[TileKey, Tile] = {}

    def put(self, key: TileKey, tile: Tile) -> None:
        self._tiles[key] = tile

    def get(self, key: TileKey) -> Tile | None:
        return self._tiles.get(key)

    def __len__(self) -> int:
        return len(self._tiles)

    def keys(self) -> list[TileKey]:
        return list(self._tiles)
