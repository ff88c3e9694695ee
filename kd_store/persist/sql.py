"""Read-only SQL over a KD: one SELECT in a transaction that is rolled back, its result
read as Arrow and, for untrusted queries, bounded in rows and bytes (:class:`ResultTooLarge`)
as it streams. :mod:`kd_store.query` sets the time limit and the sandboxed settings.
"""

from __future__ import annotations

import contextlib

import duckdb
import pyarrow as pa

from kd_store.errors import KDError, ResultTooLarge


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
