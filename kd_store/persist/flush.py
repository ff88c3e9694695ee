"""One flush of the KD to its file (:class:`Write`, :func:`write`): the frames, state rows,
expectations, events, relations, classes and map tiles that changed, each table replaced or
appended in one transaction, so a flush lands whole or not at all, also when the process
dies mid-way (DuckDB's write-ahead log is replayed on the next open). Every row is stamped
with the run it belongs to.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import duckdb
import numpy as np
import pyarrow as pa

from kd_store.classes import ClassPrototype
from kd_store.frames import EntityFrame, EventFrame
from kd_store.persist.arrow import (
    classes_to_arrow,
    entities_to_arrow,
    events_to_arrow,
    expectations_to_arrow,
    relations_to_arrow,
)
from kd_store.persist.tile_rows import tiles_to_arrow
from kd_store.relations import Relation
from kd_store.states import StateColumns, rows_to_arrow
from kd_store.tiles import MapTile


def _with_run(rows: pa.Table, run_id: int) -> pa.Table:
    return rows.append_column("run_id", pa.array(np.full(rows.num_rows, run_id, np.int64)))


@dataclass(slots=True)
class Write:
    """Everything one flush writes. Frames replace stored frames of the same id/name."""

    entities: list[EntityFrame] = field(default_factory=list)
    entity_states: dict[str, pa.Array] | None = None  # current states of ``entities``
    states: list[StateColumns] = field(default_factory=list)
    events: list[EventFrame] = field(default_factory=list)
    relations: list[Relation] = field(default_factory=list)
    classes: list[ClassPrototype] = field(default_factory=list)
    tiles: list[MapTile] = field(default_factory=list)
    next_id: int = 0
    run_id: int = 0  # of every row written

    def __bool__(self) -> bool:
        return bool(
            self.entities
            or self.states
            or self.events
            or self.relations
            or self.classes
            or self.tiles
        )


def _replace(con: duckdb.DuckDBPyConnection, table: str, key: str, rows: pa.Table) -> None:
    con.register("_kd_rows", rows)
    try:
        con.execute(f"DELETE FROM {table} WHERE {key} IN (SELECT {key} FROM _kd_rows)")
        con.execute(f"INSERT INTO {table} BY NAME SELECT * FROM _kd_rows")
    finally:
        con.unregister("_kd_rows")


def _append(con: duckdb.DuckDBPyConnection, table: str, rows: pa.Table) -> None:
    con.register("_kd_rows", rows)
    try:
        con.execute(f"INSERT INTO {table} BY NAME SELECT * FROM _kd_rows")
    finally:
        con.unregister("_kd_rows")


def write(con: duckdb.DuckDBPyConnection, w: Write) -> None:
    """Write one flush in one transaction (all Arrow, no row-by-row inserts); every row is
    stamped with ``w.run_id``."""

    def rows(table: pa.Table) -> pa.Table:
        return _with_run(table, w.run_id)

    con.execute("BEGIN TRANSACTION")
    try:
        if w.entities:
            _replace(
                con, "entity_frames", "id", rows(entities_to_arrow(w.entities, w.entity_states))
            )
            exp = expectations_to_arrow(w.entities)
            con.register("_kd_ids", pa.table({"id": [f.id for f in w.entities]}))
            con.execute(
                "DELETE FROM entity_expectation_rows WHERE entity_id IN (SELECT id FROM _kd_ids)"
            )
            con.unregister("_kd_ids")
            if exp.num_rows:
                _append(con, "entity_expectation_rows", rows(exp))
        if w.states:  # one INSERT of one contiguous table: DuckDB appends a single large
            # chunk faster than the same rows in one chunk per ingested batch
            _append(con, "entity_state_rows", rows(rows_to_arrow(w.states)))
        if w.events:
            _replace(con, "event_frames", "id", rows(events_to_arrow(w.events)))
        if w.relations:
            con.register("_kd_rows", rows(relations_to_arrow(w.relations)))
            con.execute(
                "DELETE FROM relation_rows r USING _kd_rows k WHERE r.src_id = k.src_id "
                "AND r.kind = k.kind AND r.dst_id = k.dst_id AND r.t_from_ns = k.t_from_ns"
            )
            con.execute("INSERT INTO relation_rows BY NAME SELECT * FROM _kd_rows")
            con.unregister("_kd_rows")
        if w.classes:
            _replace(con, "class_prototypes", "name", classes_to_arrow(w.classes))
        if w.tiles:
            con.register("_kd_rows", rows(tiles_to_arrow(w.tiles)))
            con.execute(
                "DELETE FROM map_tile_rows r USING "
                "(SELECT DISTINCT level, tx, ty, run_id FROM _kd_rows) k "
                "WHERE r.level = k.level AND r.tx = k.tx AND r.ty = k.ty AND r.run_id = k.run_id"
            )
            con.execute("INSERT INTO map_tile_rows BY NAME SELECT * FROM _kd_rows")
            con.unregister("_kd_rows")
        con.execute("UPDATE kd_meta SET value = ? WHERE key = 'next_id'", [str(w.next_id)])
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise
