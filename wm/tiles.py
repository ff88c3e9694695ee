"""Map tiles in the knowledge database: the maps' tile store backed by the KD's long-term memory.

Reference 001, section 4.4.11 (long-term memory contains maps; local maps update the stored
ones). Cells leaving a level's window go to the KD and come back when the vehicle
returns, also in a later run over the same KD file (docs/architecture.md, map levels and tiles;
the knowledge database, memory tiers).
This is the adapter at the edge: maps knows only its two-method
:class:`~maps.tiles.TileStore`, kd_store only named arrays under ``(level, tx, ty)``.

A level fills its first window from its store, and :func:`keep_windows` puts the last windows
of every level in at the end of a run (also those of levels that keep no tiles while running,
like the 4 cm primitive level), so the KD holds the final map. :func:`stored_maps` rebuilds
that map from the KD file alone: a stack centred on the last self pose, every cell read from
the KD's tiles, for What If and pictures without the log.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

import kd_store
from core.errors import EngineError
from core.geometry import pose_from_xyz_quat
from maps.stack import MapStack, StackConfig
from maps.tiles import Tile, TileKey

SELF_NAME = "self"  # the name the node gives the vehicle's own entity (wm.node)


class TileError(EngineError, ValueError):
    """A KD that lacks what its stored maps need (names the KD file and what is missing)."""


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


class ReadOnlyKDTileStore(KDTileStore):
    """Tiles read from a KD; cells leaving a window are dropped (the stored map stays as the
    run left it)."""

    def put(self, key: TileKey, tile: Tile) -> None:
        return None


def map_stack_over_kd(
    kd: kd_store.KnowledgeDatabase, config: StackConfig | None = None
) -> MapStack:
    """A map stack whose tiles live in ``kd``; its first windows come from the tiles there."""
    return MapStack(config, store=KDTileStore(kd))


def keep_windows(stack: MapStack) -> int:
    """Put every level's current window into the stack's tile store (at the end of a run);
    returns the tiles put. Levels that keep no tiles while running (``keep_tiles=False``)
    put their last window too, so the store holds the final map of every level."""
    n = 0
    for lvl in stack.levels:
        if lvl.store is not None:
            n += lvl.keep_window()
            continue
        lvl.store = stack.store  # for this one save only: the level stays tile-free
        try:
            n += lvl.keep_window()
        finally:
            lvl.store = None
    return n


@dataclass
class StoredMaps:
    """The map a run left in a KD, around the vehicle's last pose.

    ``stack``: every level centred on ``T_world_body`` (4x4 float64, world <- body, the self
    entity's last state), its cells read from the KD's tiles (nothing is written back).
    ``self_id``: that self entity. ``levels``: names of the levels the KD holds tiles of
    (the others are empty)."""

    stack: MapStack
    self_id: int
    T_world_body: np.ndarray
    t_ns: int
    levels: list[str]


def last_self(kd: kd_store.KnowledgeDatabase) -> kd_store.EntityFrame:
    """The newest self entity with a world-frame state (the last run's vehicle; a KD written
    by several runs holds one per run). Raises :class:`TileError` if there is none."""
    selves = [
        f
        for f in kd.entities()
        if f.name == SELF_NAME and f.state is not None and f.state.frame == "world"
    ]
    if not selves:
        raise TileError(f"KD {kd.path}: no self entity with a world-frame state (no run stored)")
    return max(selves, key=lambda f: f.id)


def stored_maps(kd: kd_store.KnowledgeDatabase, config: StackConfig | None = None) -> StoredMaps:
    """The stored map of every level of ``config`` around the last self pose (see
    :class:`StoredMaps`). ``config`` must be the one the run used (default: the default
    stack). Raises :class:`TileError` naming the KD file when it holds no map tiles."""
    config = config or StackConfig()
    held = sorted({key[0] for key in kd.tile_keys()})
    if not held:
        raise TileError(
            f"KD {kd.path} holds no map tiles; write them with `wm run LOG --kd {kd.path}`"
        )
    me = last_self(kd)
    s = me.state
    T_world_body = pose_from_xyz_quat(s.position_xyz, s.orientation_xyzw)
    # every level reads tiles here, also those that keep none while running
    levels = tuple(dataclasses.replace(c, keep_tiles=True) for c in config.levels)
    stack = MapStack(dataclasses.replace(config, levels=levels), ReadOnlyKDTileStore(kd))
    stack.move_to_pose(T_world_body)
    names = [lvl.name for lvl in stack.levels if lvl.name in held]
    return StoredMaps(stack, me.id, T_world_body, int(s.t_ns), names)
