"""Long-term memory on disk: the DuckDB adapter of the KD. Reference 001, section 4.4.11.
This package is the only part of the KD that speaks to DuckDB; everything else in the KD is
numpy and plain Python, and holds a connection only as an opaque :data:`Connection`.

One module per noun, all re-exported here (callers use ``kd_store.persist.NAME``):

- :mod:`~kd_store.persist.schema`: the file, its schema version and tables, migrations,
  runs, checkpoints (:func:`connect`).
- :mod:`~kd_store.persist.arrow`: frames as Arrow tables and back (no DuckDB).
- :mod:`~kd_store.persist.flush`: one flush (:class:`Write`, :func:`write`), as Arrow rows
  that can be held, merged and written to a replica too (:class:`Rows`).
- :mod:`~kd_store.persist.load`: what opening a KD loads (:func:`read`), state histories.
- :mod:`~kd_store.persist.tile_rows`: map tiles as ``map_tile_rows``.
- :mod:`~kd_store.persist.sql`: the one-SELECT read-only query, bounded results.
- :mod:`~kd_store.persist.parquet`: Parquet export and import.
- :mod:`~kd_store.persist.snapshots`: read-only snapshots published beside the KD.

Each :func:`write` is one transaction: a flush lands whole or not at all, also when the
process dies mid-way (DuckDB's write-ahead log is replayed on the next open).
"""

# bench/bench_kd.py reaches the schema script through ``kd_store.persist.resources``, a name
# the single module this package replaced had
from importlib import resources

from kd_store.persist.arrow import (
    classes_from_arrow,
    classes_to_arrow,
    current_states_to_arrow,
    entities_from_arrow,
    entities_to_arrow,
    events_from_arrow,
    events_to_arrow,
    expectations_from_arrow,
    expectations_to_arrow,
    relations_from_arrow,
    relations_to_arrow,
)
from kd_store.persist.flush import Rows, Write, apply_rows, merge_rows, write, write_rows
from kd_store.persist.load import Stored, read, read_states, read_states_as_of
from kd_store.persist.parquet import export_parquet, import_parquet
from kd_store.persist.schema import (
    OLDEST_VERSION,
    RUN_TABLES,
    SCHEMA_VERSION,
    TABLES,
    TABLES_SINCE,
    Connection,
    begin_run,
    checkpoint,
    connect,
    has_runs,
    latest_run,
    run_ids,
)
from kd_store.persist.snapshots import (
    SNAPSHOT_KEY,
    copy_snapshot,
    copy_with_wal,
    mark_snapshot,
    snapshot_target,
)
from kd_store.persist.sql import cursor, read_only_query
from kd_store.persist.tile_rows import read_tile, read_tile_keys, tiles_to_arrow

__all__ = [
    "OLDEST_VERSION",
    "RUN_TABLES",
    "SCHEMA_VERSION",
    "SNAPSHOT_KEY",
    "TABLES",
    "TABLES_SINCE",
    "Connection",
    "Rows",
    "Stored",
    "Write",
    "apply_rows",
    "begin_run",
    "checkpoint",
    "classes_from_arrow",
    "classes_to_arrow",
    "connect",
    "copy_snapshot",
    "copy_with_wal",
    "current_states_to_arrow",
    "cursor",
    "entities_from_arrow",
    "entities_to_arrow",
    "events_from_arrow",
    "events_to_arrow",
    "expectations_from_arrow",
    "expectations_to_arrow",
    "export_parquet",
    "has_runs",
    "import_parquet",
    "latest_run",
    "mark_snapshot",
    "merge_rows",
    "read",
    "read_only_query",
    "read_states",
    "read_states_as_of",
    "read_tile",
    "read_tile_keys",
    "relations_from_arrow",
    "relations_to_arrow",
    "resources",
    "run_ids",
    "snapshot_target",
    "tiles_to_arrow",
    "write",
    "write_rows",
]
