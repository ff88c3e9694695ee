"""One flush of the KD to its file (:class:`Write`, :func:`write`): the frames, state rows,
expectations, events, relations, classes and map tiles that changed, each table replaced or
appended in one transaction, so a flush lands whole or not at all, also when the process
dies mid-way (DuckDB's write-ahead log is replayed on the next open). Every row is stamped
with the run it belongs to. A write converted to Arrow once (:class:`Rows`) can be held,
merged with later ones (:func:`merge_rows`) and written to the file and to a replica of it
alike (:func:`write_rows`, :func:`apply_rows`).
"""

from __future__ import annotations

from collections.abc import Sequence
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

    def rows(self) -> Rows:
        """This write as the Arrow rows :func:`write_rows` writes, every row stamped with
        ``run_id``: the frames' fields as they are now."""

        def stamped(table: pa.Table) -> pa.Table:
            return _with_run(table, self.run_id)

        entities = expectations = None
        if self.entities:
            entities = stamped(entities_to_arrow(self.entities, self.entity_states))
            expectations = stamped(expectations_to_arrow(self.entities))
        return Rows(
            entities=entities,
            expectations=expectations,
            # one contiguous table: DuckDB appends a single large chunk faster than the same
            # rows in one chunk per ingested batch
            states=stamped(rows_to_arrow(self.states)) if self.states else None,
            events=stamped(events_to_arrow(self.events)) if self.events else None,
            relations=stamped(relations_to_arrow(self.relations)) if self.relations else None,
            classes=classes_to_arrow(self.classes) if self.classes else None,
            tiles=stamped(tiles_to_arrow(self.tiles)) if self.tiles else None,
            next_id=self.next_id,
        )


@dataclass(frozen=True, slots=True)
class Rows:
    """One write of the KD file as Arrow tables (:meth:`Write.rows`), converted once, so that
    the same rows can be held for a later flush, merged with others (:func:`merge_rows`) and
    written to another database too: a replica of the file (:mod:`wm.serve_sql`). Each table
    is None when nothing of its kind changed. ``entities`` replace the stored frames of the
    same ``id`` and their expectation rows with ``expectations``; ``states`` are appended;
    ``events`` replace by ``id``, ``relations`` by (src_id, kind, dst_id, t_from_ns),
    ``classes`` by ``name``, ``tiles`` whole tiles by (level, tx, ty, run_id); ``next_id`` is
    the KD's next id after it. Nothing in it is changed once made."""

    entities: pa.Table | None = None
    expectations: pa.Table | None = None
    states: pa.Table | None = None
    events: pa.Table | None = None
    relations: pa.Table | None = None
    classes: pa.Table | None = None
    tiles: pa.Table | None = None
    next_id: int = 0

    def __bool__(self) -> bool:
        return any(getattr(self, k) is not None for k in _TABLES)

    @property
    def state_rows(self) -> int:
        """Rows of ``entity_state_rows`` it appends."""
        return 0 if self.states is None else self.states.num_rows


_TABLES = ("entities", "expectations", "states", "events", "relations", "classes", "tiles")
_RELATION_KEY = ("src_id", "kind", "dst_id", "t_from_ns")
_TILE_KEY = ("level", "tx", "ty", "run_id")


def merge_rows(rows: Sequence[Rows]) -> Rows:
    """One :class:`Rows` whose write leaves a database as writing each of ``rows`` in order
    does: per key the last replacement (a frame's, a tile's, expectations with the last of
    their entity), every appended state row in order, the last ``next_id``. One write of
    the merged rows costs what one write of the largest does, not one per element."""
    rows = [r for r in rows if r]
    if len(rows) <= 1:
        return rows[0] if rows else Rows()

    def tables(name: str) -> list[tuple[int, pa.Table]]:
        return [(k, t) for k, r in enumerate(rows) if (t := getattr(r, name)) is not None]

    entities = tables("entities")
    last_of_entity = _last_source(entities, ("id",))
    return Rows(
        entities=_keep_last(entities, ("id",)),
        expectations=_of_last(tables("expectations"), ("entity_id",), last_of_entity),
        states=_concat([t for _, t in tables("states")]),
        events=_keep_last(tables("events"), ("id",)),
        relations=_keep_last(tables("relations"), _RELATION_KEY),
        classes=_keep_last(tables("classes"), ("name",)),
        tiles=_of_last(tables("tiles"), _TILE_KEY, _last_source(tables("tiles"), _TILE_KEY)),
        next_id=rows[-1].next_id,
    )


def _concat(tables: list[pa.Table]) -> pa.Table | None:
    if not tables:
        return None
    return tables[0] if len(tables) == 1 else pa.concat_tables(tables)


def _keys(table: pa.Table, key: tuple[str, ...]) -> list[tuple]:
    return list(zip(*(table.column(c).to_pylist() for c in key), strict=True))


def _last_source(tables: list[tuple[int, pa.Table]], key: tuple[str, ...]) -> dict[tuple, int]:
    """Key -> the index (in the merged sequence) of the last table holding it."""
    last: dict[tuple, int] = {}
    for k, t in tables:
        last.update(dict.fromkeys(_keys(t, key), k))
    return last


def _keep_last(tables: list[tuple[int, pa.Table]], key: tuple[str, ...]) -> pa.Table | None:
    """The rows of ``tables`` (in order) with the last row of each key only."""
    table = _concat([t for _, t in tables])
    if table is None or len(tables) == 1:
        return table
    last = {k: i for i, k in enumerate(_keys(table, key))}
    return table.take(pa.array(sorted(last.values()), pa.int64()))


def _of_last(
    tables: list[tuple[int, pa.Table]], key: tuple[str, ...], last: dict[tuple, int]
) -> pa.Table | None:
    """The rows of ``tables`` whose key's last holder (``last``) is their own table: groups
    of rows replaced whole (an entity's expectations, a tile's layers)."""
    if len(tables) <= 1:
        return _concat([t for _, t in tables])
    keep = [t.filter(pa.array([last.get(kk) == k for kk in _keys(t, key)], pa.bool_()))
            for k, t in tables]  # fmt: skip
    return _concat(keep)


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
    write_rows(con, w.rows())


def write_rows(con: duckdb.DuckDBPyConnection, rows: Rows) -> None:
    """Write ``rows`` in one transaction: it lands whole or not at all."""
    con.execute("BEGIN TRANSACTION")
    try:
        apply_rows(con, rows)
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise


def apply_rows(con: duckdb.DuckDBPyConnection, rows: Rows) -> None:
    """The statements of :func:`write_rows`, in the caller's transaction."""
    if rows.entities is not None:
        con.register("_kd_rows", rows.entities)  # once for both tables: a register costs
        try:
            con.execute("DELETE FROM entity_frames WHERE id IN (SELECT id FROM _kd_rows)")
            con.execute("INSERT INTO entity_frames BY NAME SELECT * FROM _kd_rows")
            con.execute(
                "DELETE FROM entity_expectation_rows WHERE entity_id IN (SELECT id FROM _kd_rows)"
            )
        finally:
            con.unregister("_kd_rows")
        if rows.expectations is not None and rows.expectations.num_rows:
            _append(con, "entity_expectation_rows", rows.expectations)
    if rows.states is not None:
        _append(con, "entity_state_rows", rows.states)
    if rows.events is not None:
        _replace(con, "event_frames", "id", rows.events)
    if rows.relations is not None:
        con.register("_kd_rows", rows.relations)
        try:
            con.execute(
                "DELETE FROM relation_rows r USING _kd_rows k WHERE r.src_id = k.src_id "
                "AND r.kind = k.kind AND r.dst_id = k.dst_id AND r.t_from_ns = k.t_from_ns"
            )
            con.execute("INSERT INTO relation_rows BY NAME SELECT * FROM _kd_rows")
        finally:
            con.unregister("_kd_rows")
    if rows.classes is not None:
        _replace(con, "class_prototypes", "name", rows.classes)
    if rows.tiles is not None:
        con.register("_kd_rows", rows.tiles)
        try:
            con.execute(
                "DELETE FROM map_tile_rows r USING "
                "(SELECT DISTINCT level, tx, ty, run_id FROM _kd_rows) k "
                "WHERE r.level = k.level AND r.tx = k.tx AND r.ty = k.ty AND r.run_id = k.run_id"
            )
            con.execute("INSERT INTO map_tile_rows BY NAME SELECT * FROM _kd_rows")
        finally:
            con.unregister("_kd_rows")
    con.execute("UPDATE kd_meta SET value = ? WHERE key = 'next_id'", [str(rows.next_id)])
