"""Long-term memory on disk: the DuckDB adapter (schema, Arrow conversions, batched writes,
reads, read-only SQL, Parquet export and import, snapshots). Reference 001, section 4.4.11.
This is the only module of the KD that speaks to DuckDB; everything else in the KD is numpy
and plain Python, and holds a connection only as an opaque :data:`Connection`.

Each :func:`write` is one transaction: a flush lands whole or not at all, also when the
process dies mid-way (DuckDB's write-ahead log is replayed on the next open).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import zlib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from kd_store.classes import ClassKind, ClassPrototype
from kd_store.covariance import unpack_covariance
from kd_store.errors import KDError, ResultTooLarge
from kd_store.frames import (
    ATTRIBUTE_FIELDS,
    VALUE_FIELDS,
    Attribute,
    EntityFrame,
    EventFrame,
    Level,
    State,
    Status,
    Value,
)
from kd_store.relations import Relation, RelationKind
from kd_store.states import StateColumns, rows_to_arrow
from kd_store.tiles import MapTile, TileKey

#: An open KD file (or a cursor on one); other modules pass it on without using DuckDB.
Connection = duckdb.DuckDBPyConnection

#: 1: frames, states, events, relations, classes. 2: adds ``map_tile_rows``. 3: adds
#: ``run_rows`` and a ``run_id`` on every row of the other data tables (rows of older files
#: become run 0). 4: ``fitted`` on ``class_prototypes`` (older prototypes were written
#: down, not fitted). Older files are migrated when opened for writing; read-only,
#: they are read as they are (no tiles in version 1, every row in run 0, none fitted).
SCHEMA_VERSION = 4
OLDEST_VERSION = 1
TABLES = (
    "kd_meta",
    "entity_frames",
    "entity_state_rows",
    "entity_expectation_rows",
    "event_frames",
    "relation_rows",
    "class_prototypes",
    "map_tile_rows",
    "run_rows",
)
#: Tables each schema version has (for Parquet imports of older exports).
TABLES_SINCE = {"map_tile_rows": 2, "run_rows": 3}
#: Tables whose rows belong to one run (a ``run_id`` column since version 3).
RUN_TABLES = (
    "entity_frames",
    "entity_state_rows",
    "entity_expectation_rows",
    "event_frames",
    "relation_rows",
    "map_tile_rows",
)
_ATTR = pa.struct([(k, pa.float64()) for k in ATTRIBUTE_FIELDS])
_CELL = pa.struct([("map_level", pa.int32()), ("col", pa.int64()), ("row", pa.int64())])
_STATE_COLS = ("x", "y", "z", "qx", "qy", "qz", "qw", "vx", "vy", "vz")


def connect(
    path: str | Path, read_only: bool = False, settings: dict[str, object] | None = None
) -> duckdb.DuckDBPyConnection:
    """Open (creating if needed) a KD file, or ``":memory:"``; checks the schema version.
    ``settings``: DuckDB configuration fixed when the connection opens (``lock_configuration``
    is applied last, so the connection's own progress-bar setting can still be made)."""
    where = f"KD file {path}"
    config = dict(settings or {})
    lock = bool(config.pop("lock_configuration", False))
    try:
        con = duckdb.connect(str(path), read_only=read_only, config=config)
        con.execute("SET enable_progress_bar = false")
        if lock:
            con.execute("SET lock_configuration = true")
    except duckdb.Error as e:
        raise KDError(f"{where}: cannot open ({e})") from None
    has_meta = con.execute(
        "SELECT count(*) FROM information_schema.tables WHERE table_name = 'kd_meta'"
    ).fetchall()[0][0]
    if has_meta:
        rows = con.execute("SELECT value FROM kd_meta WHERE key = 'schema_version'").fetchall()
        version = int(rows[0][0]) if rows else 0
        if version > SCHEMA_VERSION:
            con.close()
            raise KDError(
                f"{where}: schema version {version} is newer than this engine's "
                f"{SCHEMA_VERSION}; open it with a newer rcs-worldmodel"
            )
        if version < OLDEST_VERSION:
            con.close()
            raise KDError(
                f"{where}: schema version {version} is unknown (expected {OLDEST_VERSION}.."
                f"{SCHEMA_VERSION})"
            )
        if version < SCHEMA_VERSION and not read_only:
            _migrate(con, version)
    elif read_only:
        con.close()
        raise KDError(f"{where}: not a KD file (no kd_meta table) and opened read-only")
    else:
        con.execute("BEGIN TRANSACTION")
        con.execute(resources.files("kd_store").joinpath("schema.sql").read_text())
        con.execute("INSERT INTO kd_meta VALUES ('schema_version', ?)", [str(SCHEMA_VERSION)])
        con.execute("INSERT INTO kd_meta VALUES ('next_id', '0')")
        con.execute("COMMIT")
    return con


def _migrate(con: duckdb.DuckDBPyConnection, version: int) -> None:
    """Bring a file of an older schema version up to this one, in one transaction. The schema
    script only adds (``IF NOT EXISTS`` / ``OR REPLACE``), so running it again is the step,
    after the columns added since (``run_id``: rows written before runs existed are run 0,
    recorded as such in ``run_rows``)."""
    con.execute("BEGIN TRANSACTION")
    try:
        for table in RUN_TABLES:
            if _has_table(con, table) and not has_runs(con, table):
                con.execute(f"ALTER TABLE {table} ADD COLUMN run_id BIGINT NOT NULL DEFAULT 0")
        if _has_table(con, "class_prototypes") and not _has_column(
            con, "class_prototypes", "fitted"
        ):
            con.execute("ALTER TABLE class_prototypes ADD COLUMN fitted BOOLEAN DEFAULT false")
        con.execute(resources.files("kd_store").joinpath("schema.sql").read_text())
        if version < 3:
            con.execute(
                "INSERT INTO run_rows SELECT 0, ?, now()::TIMESTAMP "
                "WHERE NOT EXISTS (SELECT 1 FROM run_rows WHERE run_id = 0)",
                [f"written by schema version {version}"],
            )
        con.execute(
            "UPDATE kd_meta SET value = ? WHERE key = 'schema_version'", [str(SCHEMA_VERSION)]
        )
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise


def _has_table(con: duckdb.DuckDBPyConnection, name: str) -> bool:
    q = "SELECT count(*) FROM information_schema.tables WHERE table_name = ?"
    return bool(con.execute(q, [name]).fetchall()[0][0])


def has_runs(con: duckdb.DuckDBPyConnection, table: str = "entity_frames") -> bool:
    """Whether ``table`` has a ``run_id`` column (schema version 3 on; False for a read-only
    file of an older version, whose rows all belong to run 0)."""
    return _has_column(con, table, "run_id")


def _has_column(con: duckdb.DuckDBPyConnection, table: str, column: str) -> bool:
    q = "SELECT count(*) FROM information_schema.columns WHERE table_name = ? AND column_name = ?"
    return bool(con.execute(q, [table, column]).fetchall()[0][0])


# ---------------------------------------------------------------- runs


def latest_run(con: duckdb.DuckDBPyConnection) -> int:
    """The newest run in the file (the largest ``run_id``), 0 in a file without runs."""
    if not _has_table(con, "run_rows"):
        return 0
    rows = con.execute("SELECT max(run_id) FROM run_rows").fetchall()
    return int(rows[0][0]) if rows and rows[0][0] is not None else 0


def run_ids(con: duckdb.DuckDBPyConnection) -> list[int]:
    """Every run the file records, oldest first ([0] for a file without runs)."""
    if not _has_table(con, "run_rows"):
        return [0]
    rows = con.execute("SELECT run_id FROM run_rows ORDER BY run_id").fetchall()
    return [int(r[0]) for r in rows] or [0]


def begin_run(con: duckdb.DuckDBPyConnection, source: str, new: bool) -> int:
    """The run a writer adds to: a new one (``new``: one more than the newest, 0 in an empty
    file) or the newest; recorded in ``run_rows`` with ``source`` (the log, or what the caller
    names) when it is not there yet. Returns its ``run_id``."""
    has_row = con.execute("SELECT count(*) FROM run_rows").fetchall()[0][0] > 0
    run_id = latest_run(con) + 1 if new and has_row else latest_run(con)
    known = con.execute("SELECT count(*) FROM run_rows WHERE run_id = ?", [run_id]).fetchall()
    if not known[0][0]:
        con.execute("INSERT INTO run_rows VALUES (?, ?, now()::TIMESTAMP)", [run_id, source])
    return run_id


def _with_run(rows: pa.Table, run_id: int) -> pa.Table:
    return rows.append_column("run_id", pa.array(np.full(rows.num_rows, run_id, np.int64)))


# ---------------------------------------------------------------- frames <-> Arrow


def _state_lists(states: list[State | None]) -> dict[str, pa.Array]:
    """Nullable state columns of the ``entity_frames`` table."""
    cols: dict[str, list] = {k: [] for k in ("t_ns", "frame", *_STATE_COLS, "cov_pv", "var_rpy")}
    for s in states:
        if s is None:
            for v in cols.values():
                v.append(None)
            continue
        cols["t_ns"].append(s.t_ns)
        cols["frame"].append(s.frame)
        vals = (*s.position_xyz, *s.orientation_xyzw, *s.velocity_xyz)
        for k, v in zip(_STATE_COLS, vals, strict=True):
            cols[k].append(float(v))
        cols["cov_pv"].append(s.covariance_packed.tolist())
        cols["var_rpy"].append(s.orientation_var_rpy.tolist())
    out = {k: pa.array(v, type=pa.float64()) for k, v in cols.items() if k in _STATE_COLS}
    out["t_ns"] = pa.array(cols["t_ns"], type=pa.int64())
    out["frame"] = pa.array(cols["frame"], type=pa.string())
    out["cov_pv"] = pa.array(cols["cov_pv"], type=pa.list_(pa.float64(), 21))
    out["var_rpy"] = pa.array(cols["var_rpy"], type=pa.list_(pa.float64(), 3))
    return out


def current_states_to_arrow(
    t_ns: np.ndarray,
    frame: list[str | None],
    pos: np.ndarray,
    quat: np.ndarray,
    vel: np.ndarray,
    cov21: np.ndarray,
    var_rpy: np.ndarray,
) -> dict[str, pa.Array]:
    """Nullable state columns of ``entity_frames`` straight from arrays (N rows; a row whose
    ``frame`` is None has no state)."""
    none = np.array([f is None for f in frame], dtype=bool)
    n = len(frame)

    def col(a: np.ndarray) -> pa.Array:
        return pa.array(np.ascontiguousarray(a), mask=none)

    def fixed(a: np.ndarray, k: int) -> pa.Array:
        values = pa.array(np.ascontiguousarray(a).reshape(-1))
        return pa.FixedSizeListArray.from_arrays(values, k, mask=pa.array(none))

    vals = np.concatenate([pos, quat, vel], axis=1).reshape(n, 10)
    out = {k: col(vals[:, i]) for i, k in enumerate(_STATE_COLS)}
    out["t_ns"] = col(t_ns.astype(np.int64))
    out["frame"] = pa.array(frame, type=pa.string())
    out["cov_pv"] = fixed(cov21, 21)
    out["var_rpy"] = fixed(var_rpy, 3)
    return out


def entities_to_arrow(
    frames: list[EntityFrame], states: dict[str, pa.Array] | None = None
) -> pa.Table:
    """``entity_frames`` rows; ``states`` (from :func:`current_states_to_arrow`) replaces the
    frames' own ``state`` fields when given."""
    cols: dict[str, pa.Array | list] = {
        "id": pa.array([f.id for f in frames], type=pa.int64()),
        "name": [f.name for f in frames],
        "name_uncertainty": pa.array([f.name_uncertainty for f in frames], type=pa.float64()),
        "level": pa.array([int(f.level) for f in frames], type=pa.int8()),
        "status": [f.status.value for f in frames],
        "confidence": pa.array([f.confidence for f in frames], type=pa.float64()),
        "generic_classes": pa.array(
            [list(f.generic_classes) for f in frames], pa.list_(pa.string())
        ),
        "specific_class": pa.array([f.specific_class for f in frames], type=pa.string()),
    }
    for k in VALUE_FIELDS:
        cols[k] = pa.array([float(getattr(f.value, k)) for f in frames], type=pa.float64())
    cols["images"] = pa.array([list(f.images) for f in frames], type=pa.list_(pa.string()))
    cols["map_cells"] = pa.array(
        [[{"map_level": c[0], "col": c[1], "row": c[2]} for c in f.map_cells] for f in frames],
        type=pa.list_(_CELL),
    )
    cols["attributes"] = pa.array(
        [
            [
                (k, {n: float(getattr(a, n)) for n in ATTRIBUTE_FIELDS})
                for k, a in f.attributes.items()
            ]
            for f in frames
        ],
        type=pa.map_(pa.string(), _ATTR),
    )
    cols["created_ns"] = pa.array([f.created_ns for f in frames], type=pa.int64())
    cols["noteworthy"] = pa.array([f.noteworthy for f in frames], type=pa.bool_())
    cols.update(states if states is not None else _state_lists([f.state for f in frames]))
    return pa.table(cols)


def _state_from_row(r: dict) -> State | None:
    if r["t_ns"] is None:
        return None
    cov = unpack_covariance(np.array([r["cov_pv"]], dtype=np.float64))[0]
    return State(
        int(r["t_ns"]),
        r["frame"],
        np.array([r["x"], r["y"], r["z"]], dtype=np.float64),
        np.array([r["qx"], r["qy"], r["qz"], r["qw"]], dtype=np.float64),
        np.array([r["vx"], r["vy"], r["vz"]], dtype=np.float64),
        cov,
        np.array(r["var_rpy"], dtype=np.float64),
    )


def entities_from_arrow(
    table: pa.Table, expectations: dict[int, tuple[State, ...]] | None = None
) -> list[EntityFrame]:
    expectations = expectations or {}
    out = []
    for r in table.to_pylist():
        out.append(
            EntityFrame(
                id=int(r["id"]),
                name=r["name"],
                level=Level(r["level"]),
                status=Status(r["status"]),
                confidence=r["confidence"],
                name_uncertainty=r["name_uncertainty"],
                attributes={k: Attribute(**v) for k, v in r["attributes"]},
                state=_state_from_row(r),
                expectations=expectations.get(int(r["id"]), ()),
                generic_classes=tuple(r["generic_classes"]),
                specific_class=r["specific_class"],
                value=Value(**{k: r[k] for k in VALUE_FIELDS}),
                images=tuple(r["images"]),
                map_cells=tuple((c["map_level"], c["col"], c["row"]) for c in r["map_cells"]),
                created_ns=int(r["created_ns"]),
                noteworthy=bool(r["noteworthy"]),
            )
        )
    return out


def expectations_to_arrow(frames: list[EntityFrame]) -> pa.Table:
    ids = [f.id for f in frames for _ in f.expectations]
    states = [s for f in frames for s in f.expectations]
    chunks = StateColumns.from_states(ids, states)
    if not chunks:
        return StateColumns(
            np.zeros(0, np.int64), np.zeros(0, np.int64), "", np.zeros((0, 3)), np.zeros((0, 4)),
            np.zeros((0, 3)), np.zeros((0, 21)), np.zeros((0, 3)),
        ).to_arrow()  # fmt: skip
    return pa.concat_tables([c.to_arrow() for c in chunks])


def expectations_from_arrow(table: pa.Table) -> dict[int, tuple[State, ...]]:
    out: dict[int, list[State]] = {}
    for c in StateColumns.from_arrow(table):
        for i in range(len(c)):
            out.setdefault(int(c.entity_id[i]), []).append(c.state(i))
    return {k: tuple(sorted(v, key=lambda s: s.t_ns)) for k, v in out.items()}


def events_to_arrow(events: list[EventFrame]) -> pa.Table:
    cols: dict[str, pa.Array] = {
        "id": pa.array([e.id for e in events], type=pa.int64()),
        "name": pa.array([e.name for e in events], type=pa.string()),
        "class_name": pa.array([e.class_name for e in events], type=pa.string()),
        "t_start_ns": pa.array([e.t_start_ns for e in events], type=pa.int64()),
        "t_end_ns": pa.array([e.t_end_ns for e in events], type=pa.int64()),
        "attributes": pa.array(
            [[(k, float(v)) for k, v in e.attributes.items()] for e in events],
            type=pa.map_(pa.string(), pa.float64()),
        ),
        "level": pa.array([e.level for e in events], type=pa.int8()),
        "confidence": pa.array([e.confidence for e in events], type=pa.float64()),
        "name_uncertainty": pa.array([e.name_uncertainty for e in events], type=pa.float64()),
    }
    for k in VALUE_FIELDS:
        cols[k] = pa.array([float(getattr(e.value, k)) for e in events], type=pa.float64())
    cols["noteworthy"] = pa.array([e.noteworthy for e in events], type=pa.bool_())
    return pa.table(cols)


def events_from_arrow(table: pa.Table) -> list[EventFrame]:
    return [
        EventFrame(
            id=int(r["id"]),
            name=r["name"],
            class_name=r["class_name"],
            t_start_ns=int(r["t_start_ns"]),
            t_end_ns=None if r["t_end_ns"] is None else int(r["t_end_ns"]),
            attributes=dict(r["attributes"]),
            level=int(r["level"]),
            confidence=r["confidence"],
            name_uncertainty=r["name_uncertainty"],
            value=Value(**{k: r[k] for k in VALUE_FIELDS}),
            noteworthy=bool(r["noteworthy"]),
        )
        for r in table.to_pylist()
    ]


def relations_to_arrow(rels: list[Relation]) -> pa.Table:
    return pa.table(
        {
            "src_id": pa.array([r.src for r in rels], type=pa.int64()),
            "kind": pa.array([r.kind.value for r in rels], type=pa.string()),
            "dst_id": pa.array([r.dst for r in rels], type=pa.int64()),
            "t_from_ns": pa.array([r.t_from_ns for r in rels], type=pa.int64()),
            "t_to_ns": pa.array([r.t_to_ns for r in rels], type=pa.int64()),
        }
    )


def relations_from_arrow(table: pa.Table) -> list[Relation]:
    return [
        Relation(r["src_id"], RelationKind(r["kind"]), r["dst_id"], r["t_from_ns"], r["t_to_ns"])
        for r in table.to_pylist()
    ]


def classes_to_arrow(protos: list[ClassPrototype]) -> pa.Table:
    m = pa.map_(pa.string(), pa.float64())
    cols: dict[str, pa.Array] = {
        "name": pa.array([p.name for p in protos], type=pa.string()),
        "kind": pa.array([p.kind.value for p in protos], type=pa.string()),
        "level": pa.array([int(p.level) for p in protos], type=pa.int8()),
        "is_a": pa.array([p.is_a for p in protos], type=pa.string()),
        "attributes": pa.array([list(p.attributes.items()) for p in protos], type=m),
        "weights": pa.array([list(p.weights.items()) for p in protos], type=m),
    }
    for k in VALUE_FIELDS:
        cols[k] = pa.array([float(getattr(p.value, k)) for p in protos], type=pa.float64())
    cols["fitted"] = pa.array([p.fitted for p in protos], type=pa.bool_())
    return pa.table(cols)


def classes_from_arrow(table: pa.Table) -> list[ClassPrototype]:
    return [
        ClassPrototype(
            name=r["name"],
            kind=ClassKind(r["kind"]),
            level=Level(r["level"]),
            is_a=r["is_a"],
            attributes=dict(r["attributes"]),
            weights=dict(r["weights"]),
            value=Value(**{k: r[k] for k in VALUE_FIELDS}),
            fitted=bool(r.get("fitted") or False),  # files before schema version 4: none
        )
        for r in table.to_pylist()
    ]


# ---------------------------------------------------------------- one flush


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


@dataclass(slots=True)
class Stored:
    """What a KD file holds, as frames (state histories stay on disk)."""

    entities: list[EntityFrame]
    events: list[EventFrame]
    relations: list[Relation]
    classes: list[ClassPrototype]
    next_id: int


def read(con: duckdb.DuckDBPyConnection, run_id: int | None = None) -> Stored:
    """Run ``run_id``'s frames, events and relations (every run's when None), and the classes
    (shared by all runs)."""

    def table(name: str, order: str = "") -> pa.Table:
        where = "" if run_id is None else f" WHERE run_id = {int(run_id)}"
        return con.sql(f"SELECT * FROM {name}{where}{order}").to_arrow_table()

    exp = expectations_from_arrow(table("entity_expectation_rows"))
    rows = con.execute("SELECT value FROM kd_meta WHERE key = 'next_id'").fetchall()
    return Stored(
        entities=entities_from_arrow(table("entity_frames", " ORDER BY id"), exp),
        events=events_from_arrow(table("event_frames", " ORDER BY id")),
        relations=relations_from_arrow(table("relation_rows")),
        classes=classes_from_arrow(con.sql("SELECT * FROM class_prototypes").to_arrow_table()),
        next_id=int(rows[0][0]) if rows else 0,
    )


def read_states(con: duckdb.DuckDBPyConnection, entity_id: int) -> list[State]:
    """One entity's long-term state history, oldest first."""
    t = con.sql(
        "SELECT * FROM entity_state_rows WHERE entity_id = $1 ORDER BY t_ns", params=[entity_id]
    ).to_arrow_table()
    states = [c.state(i) for c in StateColumns.from_arrow(t) for i in range(len(c))]
    return sorted(states, key=lambda s: s.t_ns)


def read_states_as_of(con: duckdb.DuckDBPyConnection, t_ns: int) -> list[StateColumns]:
    """Each entity's latest long-term state at or before ``t_ns`` (the
    ``entity_states_as_of`` macro of every run in the file)."""
    table = con.sql("SELECT * FROM entity_states_as_of($1)", params=[int(t_ns)]).to_arrow_table()
    return StateColumns.from_arrow(table)


def checkpoint(con: duckdb.DuckDBPyConnection) -> None:
    """Fold DuckDB's write-ahead log into the file."""
    con.execute("CHECKPOINT")


# ---------------------------------------------------------------- map tiles


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


# ---------------------------------------------------------------- read-only SQL


def cursor(con: duckdb.DuckDBPyConnection) -> duckdb.DuckDBPyConnection:
    """A cursor of ``con`` for one reader (its own transactions), without a progress bar."""
    cur = con.cursor()
    with contextlib.suppress(duckdb.Error):  # a locked configuration keeps its own setting
        cur.execute("SET enable_progress_bar = false")
    return cur


def read_only_query(
    cur: duckdb.DuckDBPyConnection,
    query: str,
    own_tx: bool = True,
    max_rows: int | None = None,
    max_bytes: int | None = None,
) -> pa.Table:
    """One SELECT in a transaction that is rolled back, so even a query with side effects
    leaves nothing behind. With ``max_rows`` or ``max_bytes`` (bytes of Arrow buffers) the
    result is read batch by batch and refused (ResultTooLarge, a KDError naming the limit and
    the query) as
    soon as it passes either, so an untrusted query cannot make the caller hold a result of
    any size; None: no limit (the engine's own queries)."""
    try:
        statements = duckdb.extract_statements(query)
    except duckdb.Error as e:
        raise KDError(f"SQL {query!r}: {e}") from None
    if len(statements) != 1 or statements[0].type != duckdb.StatementType.SELECT:
        kinds = [s.type.name for s in statements]
        raise KDError(f"SQL {query!r}: only one read-only SELECT is allowed, got {kinds}")
    if own_tx:
        cur.execute("BEGIN TRANSACTION")
    try:
        rel = cur.sql(query)
        if max_rows is None and max_bytes is None:
            return rel.to_arrow_table()
        return _bounded_arrow(rel, query, max_rows, max_bytes)
    except duckdb.PermissionException as e:
        raise KDError(
            f"SQL {query!r}: refused, a KD's SQL reads the KD's own views only (docs/kd.md), "
            f"no file, URL or extension outside it ({e})"
        ) from None
    except (duckdb.Error, pa.ArrowException, OSError) as e:
        # a failure while a streamed result is read (an error() call, an interrupt at the
        # time limit) reaches Python through Arrow's stream as OSError or an Arrow error
        raise KDError(f"SQL {query!r}: {e}") from None
    finally:
        if own_tx:
            cur.execute("ROLLBACK")


# rows per Arrow batch of a bounded result: the limits are checked batch by batch, so at most
# this many rows beyond a limit are ever read
_BATCH_ROWS = 65_536


def _bounded_arrow(
    rel: duckdb.DuckDBPyRelation, query: str, max_rows: int | None, max_bytes: int | None
) -> pa.Table:
    """``rel``'s result as Arrow, read through a record-batch reader and refused with
    ResultTooLarge as soon as it holds more than ``max_rows`` rows or ``max_bytes`` bytes
    (None: that limit is off). DuckDB streams the result, so a refused query stops there."""
    rows_cap = max_rows if max_rows is not None else _BATCH_ROWS
    # older DuckDB (1.0) names the reader fetch_arrow_reader
    to_reader = getattr(rel, "to_arrow_reader", None) or rel.fetch_arrow_reader
    reader = to_reader(max(1, min(rows_cap + 1, _BATCH_ROWS)))
    schema = reader.schema
    batches: list[pa.RecordBatch] = []
    rows = size = 0
    try:
        for batch in reader:
            rows, size = rows + batch.num_rows, size + batch.nbytes
            if max_rows is not None and rows > max_rows:
                raise ResultTooLarge(
                    f"SQL {query!r}: the result has more than the limit of {max_rows:,} rows "
                    f"(max_rows); narrow it (WHERE, LIMIT, an aggregate) or raise the limit"
                )
            if max_bytes is not None and size > max_bytes:
                raise ResultTooLarge(
                    f"SQL {query!r}: the result passed the limit of {_mb(max_bytes)} "
                    f"(max_bytes) at {_mb(size)} after {rows:,} rows; narrow it (fewer "
                    f"columns or rows, shorter values) or raise the limit"
                )
            batches.append(batch)
    finally:
        reader.close()
    return pa.Table.from_batches(batches, schema=schema)


def _mb(n_bytes: int) -> str:
    """``n_bytes`` as MB (2**20 bytes) for a message."""
    return f"{n_bytes / 2**20:,.1f} MB"


# ---------------------------------------------------------------- Parquet


def export_parquet(con: duckdb.DuckDBPyConnection, folder: str | Path) -> list[Path]:
    """One ``<table>.parquet`` per base table in ``folder``; returns the files written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for name in TABLES:
        if not _has_table(con, name):  # a read-only file of an older schema version
            continue
        path = folder / f"{name}.parquet"
        pq.write_table(con.sql(f"SELECT * FROM {name}").to_arrow_table(), path)
        out.append(path)
    return out


def import_parquet(con: duckdb.DuckDBPyConnection, folder: str | Path) -> None:
    """Load a folder written by :func:`export_parquet` into an empty KD, in one transaction."""
    folder = Path(folder)
    if not (folder / "kd_meta.parquet").is_file():
        raise KDError(f"Parquet KD {folder}: missing kd_meta.parquet")
    meta = {r["key"]: r["value"] for r in pq.read_table(folder / "kd_meta.parquet").to_pylist()}
    version = int(meta.get("schema_version", 0))
    if not OLDEST_VERSION <= version <= SCHEMA_VERSION:
        raise KDError(
            f"Parquet KD {folder}: schema version {version}, this engine reads "
            f"{OLDEST_VERSION}..{SCHEMA_VERSION}"
        )
    tables = [n for n in TABLES if TABLES_SINCE.get(n, OLDEST_VERSION) <= version]
    missing = [n for n in tables if not (folder / f"{n}.parquet").is_file()]
    if missing:
        raise KDError(f"Parquet KD {folder}: missing {', '.join(m + '.parquet' for m in missing)}")
    n = con.execute(
        "SELECT (SELECT count(*) FROM entity_frames) + (SELECT count(*) FROM event_frames)"
    ).fetchall()[0][0]
    if n:
        raise KDError(f"Parquet KD {folder}: the target KD already holds {n} frames")
    con.execute("BEGIN TRANSACTION")
    try:
        for name in tables[1:]:
            _replace_all(con, name, pq.read_table(folder / f"{name}.parquet"))
        con.execute("UPDATE kd_meta SET value = ? WHERE key = 'next_id'", [meta["next_id"]])
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise


def _replace_all(con: duckdb.DuckDBPyConnection, table: str, rows: pa.Table) -> None:
    con.execute(f"DELETE FROM {table}")
    _append(con, table, rows)


# ---------------------------------------------------------------- read-only snapshots

#: kd_meta key naming where a KD publishes its snapshots (absolute path). A snapshot is a
#: byte copy of its KD, so it carries the key too: a file whose key names its own path is a
#: snapshot published there, which the next publication may replace.
SNAPSHOT_KEY = "snapshot_path"
_DUCKDB_MAGIC = b"DUCK"  # at byte 8 of every DuckDB file


def snapshot_target(kd_path: str | Path, snapshot_path: str | Path) -> Path:
    """The absolute path a snapshot of the KD file ``kd_path`` may be published at, or a
    KDError saying why not. The rule: ``snapshot_path`` is not the KD (nor its ``.wal``), its
    folder exists, and it either does not exist or is a snapshot published there before (a
    KD file whose ``snapshot_path`` meta key names it); anything else there (another KD, the
    log, any other file) is never replaced."""
    where = f"snapshot {snapshot_path}"
    if str(kd_path) == ":memory:":
        raise KDError(f"{where}: a throwaway KD (':memory:') has no file to publish")
    target, kd = Path(snapshot_path).resolve(), Path(kd_path).resolve()
    if target in (kd, Path(f"{kd}.wal")):
        raise KDError(f"{where}: is the KD file itself; give another path")
    if not target.parent.is_dir():
        raise KDError(f"{where}: folder {target.parent} does not exist")
    if target.is_dir():
        raise KDError(f"{where}: is a folder; give a file name")
    if target.exists() and not _is_snapshot_at(target):
        raise KDError(
            f"{where}: the file exists and is no snapshot published there before; "
            "remove it or give another path"
        )
    return target


def _is_snapshot_at(path: Path) -> bool:
    """``path`` is a DuckDB KD file whose ``snapshot_path`` meta key names ``path``."""
    with path.open("rb") as f:
        if f.read(12)[8:12] != _DUCKDB_MAGIC:
            return False
    try:  # plain DuckDB: the KD's connect would refuse or migrate a file of another version
        con = duckdb.connect(str(path), read_only=True)
    except duckdb.Error:
        return False  # not readable (or another process writes it): not ours to replace
    try:
        if not _has_table(con, "kd_meta"):
            return False
        rows = con.execute("SELECT value FROM kd_meta WHERE key = ?", [SNAPSHOT_KEY]).fetchall()
    except duckdb.Error:
        return False
    finally:
        con.close()
    return bool(rows) and rows[0][0] == str(path)


def mark_snapshot(con: duckdb.DuckDBPyConnection, target: Path) -> None:
    """Record in the KD's meta table that its snapshots go to ``target`` (absolute), in one
    transaction; the snapshots copy it, which is how a later publication recognises them."""
    con.execute("BEGIN TRANSACTION")
    try:
        con.execute("DELETE FROM kd_meta WHERE key = ?", [SNAPSHOT_KEY])
        con.execute("INSERT INTO kd_meta VALUES (?, ?)", [SNAPSHOT_KEY, str(target)])
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise


def copy_snapshot(kd_path: Path, target: Path) -> None:
    """Copy the checkpointed KD file ``kd_path`` (no write-ahead log left: everything is in
    the file) onto ``target`` atomically: into ``.<name>.partial`` beside it, fsync, then
    ``os.replace``. A reader never sees a half-written file, and one that has the old
    snapshot open keeps its inode. A ``.wal`` beside the target is removed first: read-only
    opens never write one, and a stale one would be replayed into the new snapshot."""
    wal = Path(f"{kd_path}.wal")
    if wal.exists() and wal.stat().st_size:
        raise KDError(f"KD file {kd_path}: write-ahead log not empty after CHECKPOINT")
    partial = target.with_name(f".{target.name}.partial")
    try:
        shutil.copyfile(kd_path, partial)  # overwrites a partial a killed run left
        fd = os.open(partial, os.O_RDONLY)
        try:
            os.fsync(fd)  # the bytes are on disk before the name points at them
        finally:
            os.close(fd)
        Path(f"{target}.wal").unlink(missing_ok=True)
        os.replace(partial, target)
        _fsync_dir(target.parent)
    except OSError as e:
        partial.unlink(missing_ok=True)
        raise KDError(f"snapshot {target}: cannot publish ({e})") from None


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (POSIX; a no-op where folders cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
