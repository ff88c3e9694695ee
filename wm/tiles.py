"""Map tiles in the knowledge database: the maps' tile store backed by the KD's long-term memory.

Reference 001, 4.4.11 (line 782: long-term memory contains maps; 784: local maps update the
stored ones). Cells leaving a level's window go to the KD and come back when the vehicle
returns, also in a later run over the same KD file (DESIGN.md section 5, memory tiers).
This is the adapter at the edge: maps knows only its two-method
:class:`~maps.tiles.TileStore`, kd_store only named arrays under ``(level, tx, ty)``.

A level fills its first window from its store, and :func:`keep_windows` puts the last windows
in at the end of a run, so the next run over the same KD file starts from them.
"""

from __future__ import annotations

import kd_store
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
    """A map stack whose tiles live in ``kd``; its first windows come from the tiles there."""
    return MapStack(config, store=KDTileStore(kd))


def keep_windows(stack: MapStack) -> int:
    """Put every level's current window into the KD (at the end of a run); returns the tiles
    put."""
    return stack.keep_windows()
