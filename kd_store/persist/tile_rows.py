"""Map tiles in the KD file: ``map_tile_rows``, one row per layer of a tile (level name, tile
indices ``tx, ty``, layer, numpy dtype and shape, the array's bytes zlib-compressed, ``t_ns``
int64 ns of its last change), written by :func:`kd_store.persist.flush.write` with the rest
of a flush and read back one tile at a time (:class:`kd_store.tiles.TileMemory`).
"""

from __future__ import annotations

import zlib

import duckdb
import numpy as np
import pyarrow as pa

from kd_store.errors import KDError
from kd_store.persist.schema import _has_table
from kd_store.tiles import MapTile, TileKey


def tiles_to_arrow(tiles: list[MapTile]) -> pa.Table:
    """``map_tile_rows`` rows: one per layer of each tile, data zlib-compressed (level 1)."""
    rows = [(t, name, a) for t in tiles for name, a in t.layers.items()]
    return pa.table(
        {
            "level": pa.array([t.key[0] for t, _, _ in rows], pa.string()),
            "tx": pa.array([t.key[1] for t, _, _ in rows], pa.int64()),
            "ty": pa.array([t.key[2] for t, _, _ in rows], pa.int64()),
            "layer": pa.array([name for _, name, _ in rows], pa.string()),
            "dtype": pa.array([a.dtype.str for _, _, a in rows], pa.string()),
            "shape": pa.array([list(a.shape) for _, _, a in rows], pa.list_(pa.int32())),
            "data": pa.array([zlib.compress(a.tobytes(), 1) for _, _, a in rows], pa.binary()),
            "t_ns": pa.array([t.t_ns for t, _, _ in rows], pa.int64()),
        }
    )


def _run_clause(run_id: int | None) -> str:
    return "" if run_id is None else f" AND run_id = {int(run_id)}"


def read_tile_keys(con: duckdb.DuckDBPyConnection, run_id: int | None = None) -> list[TileKey]:
    """Keys of every tile of run ``run_id`` (of every run when None, as in a file older than
    schema version 3; none in a read-only file of version 1)."""
    if not _has_table(con, "map_tile_rows"):
        return []
    rows = con.execute(
        f"SELECT DISTINCT level, tx, ty FROM map_tile_rows WHERE TRUE{_run_clause(run_id)}"
    ).fetchall()
    return [(str(lv), int(tx), int(ty)) for lv, tx, ty in rows]


def read_tile(
    con: duckdb.DuckDBPyConnection, key: TileKey, run_id: int | None = None
) -> MapTile | None:
    """One stored tile of run ``run_id`` (as :func:`read_tile_keys`), or None. Refuses a row
    whose bytes do not match its dtype and shape."""
    rows = con.execute(
        "SELECT layer, dtype, shape, data, t_ns FROM map_tile_rows "
        f"WHERE level = ? AND tx = ? AND ty = ?{_run_clause(run_id)}",
        list(key),
    ).fetchall()
    if not rows:
        return None
    layers = {}
    for layer, dtype, shape, data, _ in rows:
        try:
            flat = np.frombuffer(zlib.decompress(data), dtype=np.dtype(dtype))
            layers[layer] = flat.reshape(shape).copy()
        except (zlib.error, TypeError, ValueError) as e:
            raise KDError(f"map tile {key}: layer {layer!r} cannot be read ({e})") from None
    return MapTile(key, layers, int(max(r[4] for r in rows)))
