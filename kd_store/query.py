"""Read-only SQL over a KD: readers for other threads, and SQL from outside the engine.

Reference 001, section 4.4 (the KD answers queries about what it holds). A
:class:`SQLReader` is one thread's read-only view of a KD being written (its own cursor, a
consistent snapshot per query); :func:`query_file` and :func:`query_reader` run SQL from
outside the engine (a command line, a network client) over a KD file or a live KD.

The text is not trusted: the connection is opened read-only with DuckDB's external access off
(no other file, directory, URL or extension can be reached: ``read_csv('/etc/passwd')``,
``COPY ... TO``, ``ATTACH``, ``INSTALL``/``LOAD`` are refused by DuckDB itself, not by parsing),
its configuration locked (``SET``, ``PRAGMA`` cannot lift the limits), a memory limit (it
bounds DuckDB's operators: sorts, joins, aggregates; not one huge value in the result, such as
``repeat('x', 2000000000)``, which DuckDB builds outside it) and a time limit; and one SELECT
only (:func:`kd_store.persist.read_only_query`). The result is read batch by batch and refused
once it passes a row or byte limit, so a ``SELECT * FROM range(10_000_000)`` stops at the limit
instead of being held whole; one huge value is refused by the byte limit, but only after DuckDB
has built it. The views are those of docs/kd.md.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa

from kd_store import persist
from kd_store.errors import KDError, ResultTooLarge

MB = 2**20  # bytes


@dataclass(frozen=True)
class QueryLimits:
    """What one untrusted query may use: DuckDB's ``memory_limit`` (e.g. ``"1GB"``), its
    worker ``threads``, ``timeout_s`` seconds of wall time before it is interrupted, and a
    result of at most ``max_rows`` rows and ``max_bytes`` bytes (Arrow buffers); a larger
    result is refused with a KDError naming the limit, not truncated."""

    memory_limit: str = "1GB"
    threads: int = 2
    timeout_s: float = 30.0
    max_rows: int = 1_000_000
    max_bytes: int = 256 * MB

    def __post_init__(self) -> None:
        if not self.timeout_s > 0 or self.threads < 1:
            raise KDError(
                f"query limits: timeout_s {self.timeout_s} must be > 0 and threads "
                f"{self.threads} >= 1"
            )
        if self.max_rows < 0 or self.max_bytes < 1:
            raise KDError(
                f"query limits: max_rows {self.max_rows} must be >= 0 and max_bytes "
                f"{self.max_bytes} >= 1"
            )


class SQLReader:
    """Read-only SQL on its own DuckDB cursor (use one per thread)."""

    def __init__(self, cursor: persist.Connection) -> None:
        self._cur = cursor
        self._in_tx = False

    def sql(
        self, query: str, max_rows: int | None = None, max_bytes: int | None = None
    ) -> pa.Table:
        """One read-only SELECT; a result of more than ``max_rows`` rows or ``max_bytes``
        bytes (Arrow buffers) is refused with a KDError before it is read whole (None: no
        limit)."""
        return persist.read_only_query(
            self._cur, query, own_tx=not self._in_tx, max_rows=max_rows, max_bytes=max_bytes
        )

    @contextmanager
    def snapshot(self) -> Iterator[SQLReader]:
        """Run several queries against one snapshot: ``with r.snapshot(): r.sql(...); ...``."""
        self._cur.execute("BEGIN TRANSACTION")
        self._in_tx = True
        try:
            yield self
        finally:
            self._in_tx = False
            self._cur.execute("ROLLBACK")

    def interrupt(self) -> None:
        """Stop the query running on this reader (from another thread)."""
        self._cur.interrupt()

    def close(self) -> None:
        self._cur.close()


def kd_settings() -> dict[str, object]:
    """The DuckDB configuration every KD is opened with (:func:`kd_store.open`): its SQL
    reaches the KD's own tables and views only, never another file, directory, URL or
    extension, and the configuration is locked so nothing run later lifts that. The engine
    needs nothing outside: its writes register Arrow tables, and Parquet export and import go
    through pyarrow, not DuckDB."""
    return {
        "enable_external_access": False,
        "autoinstall_known_extensions": False,
        "autoload_known_extensions": False,
        "lock_configuration": True,
    }


def sandbox_settings(limits: QueryLimits) -> dict[str, object]:
    """The DuckDB configuration of an untrusted query's connection."""
    return {**kd_settings(), "memory_limit": limits.memory_limit, "threads": limits.threads}


def served_settings(limits: QueryLimits = QueryLimits()) -> dict[str, object]:
    """The DuckDB configuration of a KD a live node writes while serving untrusted SQL over it
    (:mod:`wm.serve`): external access off, the configuration locked and ``limits.threads``
    worker threads (2 by default) as for :func:`query_file`; the memory limit bounds the
    writer too, so it is not set here."""
    return {k: v for k, v in sandbox_settings(limits).items() if k not in ("memory_limit",)}


def query_reader(reader: SQLReader, sql: str, limits: QueryLimits = QueryLimits()) -> pa.Table:
    """One read-only SELECT through ``reader`` (a :class:`SQLReader` of a KD
    opened with :func:`served_settings`), interrupted after ``limits.timeout_s`` and refused
    past ``limits.max_rows`` rows or ``limits.max_bytes`` bytes."""
    return _time_limited(
        sql,
        limits,
        lambda: reader.sql(sql, max_rows=limits.max_rows, max_bytes=limits.max_bytes),
        reader.interrupt,
    )


def _time_limited(sql: str, limits: QueryLimits, run, interrupt) -> pa.Table:
    """``run()`` with ``interrupt()`` called after ``limits.timeout_s``; a query stopped so
    raises KDError saying it was the time limit (a result refused for its size keeps its own
    words: DuckDB finishes building one huge value before it sees the interrupt)."""
    timer = threading.Timer(limits.timeout_s, interrupt)
    timer.start()
    try:
        return run()
    except ResultTooLarge:
        raise  # the size limit is what stopped it, even when the timer fired meanwhile
    except KDError:
        if not timer.is_alive():
            raise KDError(f"SQL {sql!r}: stopped after the {limits.timeout_s:g} s limit") from None
        raise
    finally:
        timer.cancel()


def query_file(path: str | Path, sql: str, limits: QueryLimits = QueryLimits()) -> pa.Table:
    """One read-only SELECT over the KD file ``path`` in a sandboxed connection; the result as
    Arrow. Raises KDError naming the query for anything refused, failed, timed out or over
    the result limits (``limits.max_rows``, ``limits.max_bytes``)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"KD file {p} does not exist")
    con = persist.connect(p, read_only=True, settings=sandbox_settings(limits))
    try:
        return _time_limited(
            sql,
            limits,
            lambda: persist.read_only_query(
                con, sql, max_rows=limits.max_rows, max_bytes=limits.max_bytes
            ),
            con.interrupt,
        )
    finally:
        con.close()
