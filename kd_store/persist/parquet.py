"""A KD as Parquet: one ``<table>.parquet`` file per base table of the schema, exported from a
KD file and imported into an empty one (files of an older schema version too).
"""

from __future__ import annotations

from pathlib import Path

import duckdb
import pyarrow as pa
import pyarrow.parquet as pq

from kd_store.errors import KDError
from kd_store.persist.flush import _append
from kd_store.persist.schema import (
    OLDEST_VERSION,
    SCHEMA_VERSION,
    TABLES,
    TABLES_SINCE,
    _has_table,
)


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
