"""The KD file itself: opening it, its schema version and tables, migrations of older files,
the runs it records, and checkpoints. Reference 001, section 4.4.11.

A KD file is one DuckDB database created by ``kd_store/schema.sql``: base tables (``TABLES``)
and the documented views over them. ``kd_meta`` holds the schema version and the next id;
``run_rows`` the runs (``wm run --append``), and every other data table a ``run_id`` per row
(:data:`RUN_TABLES`). A file of an older version is migrated when opened for writing, in one
transaction, and read as it is when opened read-only.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import duckdb

from kd_store.errors import KDError

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


def checkpoint(con: duckdb.DuckDBPyConnection) -> None:
    """Fold DuckDB's write-ahead log into the file."""
    con.execute("CHECKPOINT")
