"""Long-term memory of map tiles: blocks of map layers kept in the KD file.

Reference 001, section 4.4.11 ("long-term memory will contain maps"; local maps from
sensory input update the stored ones). A tile is a set of named layers, each an array of
any numeric dtype and shape, keyed by ``(level name, tx, ty)``: the map level and the tile's
integer index in that level's fixed world grid (what the indices mean is the map's business;
see ``maps/tiles.py``). The KD keeps the arrays, not their meaning.

In RAM: tiles put since the last write (pending) and a bounded cache of recently used clean
tiles; on disk, the ``map_tile_rows`` table (one row per tile layer, written by
:mod:`kd_store.persist` in the same transaction as the rest of a flush, so a tile is on disk
whole or not at all). Arrays go in and come out as copies.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from kd_store.errors import KDError

TileKey = tuple[str, int, int]  # (level name, tx, ty)
_INT64 = (-(2**63), 2**63 - 1)


@dataclass(slots=True)
class MapTile:
    """One tile: ``layers`` maps layer name -> array (owned by the KD), written at ``t_ns``."""

    key: TileKey
    layers: dict[str, np.ndarray]
    t_ns: int

    def copy_layers(self) -> dict[str, np.ndarray]:
        return {name: a.copy() for name, a in self.layers.items()}


def check_tile(level: object, tx: object, ty: object, layers: object, t_ns: object) -> MapTile:
    """Refuse a bad key, time or layer set (message names the tile); returns a tile holding
    C-contiguous copies of the arrays."""
    where = f"map tile ({level!r}, {tx!r}, {ty!r})"
    if not isinstance(level, str) or not level:
        raise KDError(f"{where}: level must be a non-empty name")
    for name, v in (("tx", tx), ("ty", ty), ("t_ns", t_ns)):
        if not isinstance(v, int | np.integer) or not _INT64[0] <= int(v) <= _INT64[1]:
            raise KDError(f"{where}: {name} {v!r} is not an int64")
    if not isinstance(layers, Mapping) or not layers:
        raise KDError(f"{where}: layers must be a non-empty mapping name -> array")
    out = {}
    for name, a in layers.items():
        if not isinstance(name, str) or not name:
            raise KDError(f"{where}: layer name {name!r} is not a non-empty string")
        arr = np.asarray(a)
        if arr.dtype.kind not in "biuf" or arr.ndim == 0:
            raise KDError(
                f"{where}: layer {name!r} has dtype {arr.dtype} and shape {arr.shape}; "
                "expected a numeric array of at least one dimension"
            )
        out[name] = np.array(arr, order="C", copy=True)
    return MapTile((level, int(tx), int(ty)), out, int(t_ns))


class TileMemory:
    """Pending tiles, a cache of clean ones and the set of keys on disk (loaded on first use).

    ``read_keys()`` lists the keys on disk; ``read_tile(key)`` reads one (or None);
    ``write(tiles)`` writes pending tiles on their own once ``write_batch`` of them wait (one
    transaction; False: not written, e.g. a read-only KD). All are given by the store, so this
    class never touches DuckDB itself.
    """

    def __init__(
        self,
        read_keys: Callable[[], Iterable[TileKey]],
        read_tile: Callable[[TileKey], MapTile | None],
        cache_tiles: int,
        write: Callable[[list[MapTile]], bool] | None = None,
        write_batch: int = 64,
    ) -> None:
        self._read_keys = read_keys
        self._read_tile = read_tile
        self._cache_tiles = cache_tiles
        self._write = write
        self._write_batch = write_batch
        self.pending: dict[TileKey, MapTile] = {}
        self._cache: OrderedDict[TileKey, MapTile] = OrderedDict()
        self._stored: set[TileKey] | None = None

    def stored(self) -> set[TileKey]:
        if self._stored is None:
            self._stored = set(self._read_keys())
        return self._stored

    def put(self, tile: MapTile) -> None:
        """Keep ``tile`` pending (replacing its key whole); bounded RAM: a full batch of
        pending tiles is written on its own."""
        self._cache.pop(tile.key, None)
        self.pending[tile.key] = tile
        if self._write is not None and len(self.pending) >= self._write_batch:
            tiles = list(self.pending.values())
            if self._write(tiles):
                self.written(tiles)

    def get(self, key: TileKey) -> dict[str, np.ndarray] | None:
        tile = self.pending.get(key)
        if tile is None:
            tile = self._cache.get(key)
            if tile is not None:
                self._cache.move_to_end(key)
            elif key in self.stored():
                tile = self._read_tile(key)
                if tile is not None:
                    self._remember(tile)
        return None if tile is None else tile.copy_layers()

    def keys(self) -> list[TileKey]:
        return sorted(self.stored() | set(self.pending))

    def written(self, tiles: list[MapTile]) -> None:
        """``tiles`` are on disk now: no longer pending, kept in the clean cache."""
        keys = self.stored()
        for t in tiles:
            if self.pending.get(t.key) is t:
                del self.pending[t.key]
            keys.add(t.key)
            self._remember(t)

    def reset(self) -> None:
        """Forget RAM and the key set (after the file changed underneath, e.g. an import)."""
        self.pending.clear()
        self._cache.clear()
        self._stored = None

    def _remember(self, tile: MapTile) -> None:
        self._cache[tile.key] = tile
        self._cache.move_to_end(tile.key)
        while len(self._cache) > self._cache_tiles:
            self._cache.popitem(last=False)
