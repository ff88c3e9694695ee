"""SQL of a live node in a process of its own (:mod:`wm.serve_proc`), answered in the server's
process from a read-only copy of the KD, so that no query costs the node's process anything.

DuckDB lets no other process open a file that one process writes, so the server cannot read
the node's KD file itself. Instead, while clients ask for SQL (the demand key :data:`SQL_KEY`,
held :data:`~wm.serve_copy.DEMAND_TTL_S` s after the last ask), a thread in the node's process
(:class:`CopyPublisher`) copies the KD as of the node's last flush at most every
``period_s`` s of wall time (:data:`SQL_COPY_PERIOD_S` by default), and only when a flush
landed since the copy before: the file and its write-ahead log, between two cycles, under the
node's lock (:meth:`kd_store.store.KnowledgeDatabase.copy_committed`; no CHECKPOINT, no fsync,
so the node pays only the bytes copied). Each copy goes to a new name in a folder of the
server's; the node keeps the newest :data:`KEEP_COPIES` and tells the server of each with its
news (:class:`SQLCopy`). The server (:class:`SQLCopies`) opens the newest read-only in a thread
of its own, which replays the copy's log into memory (tens of ms, not on a request's path),
configured as every untrusted query's connection (:func:`kd_store.query.open_copy`: DuckDB's
external access off, its configuration locked, a memory and a thread limit), then answers each
query on a cursor of its own within the time, row and byte limits (:func:`kd_store.query.
query_reader`). A copy being read when a newer one is opened is closed and removed once its last
query ends.

Staleness: an answer is as of the copy's cycle (``cycle_t_ns``: the cycle whose flush the copy
holds), which is behind the newest cycle by up to the flush interval (1 s of log time) plus the
copy period plus the copy's open in the server; the answer says by how much
(``staleness_ns``), ``/v1/status`` (``sql``) the copy's age in wall time. Before the first copy
(or while the first is opened) a query is a 503 that says so, with ``Retry-After``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa

from wm.serve import ServeError

log = logging.getLogger(__name__)

#: the demand key a SQL request notes (:class:`wm.serve_copy.ServedDemand`)
SQL_KEY = "sql"
#: the node copies its KD for SQL at most this often, s of wall time
SQL_COPY_PERIOD_S = 2.0
#: copies the node keeps in the folder (the newest and the one before, which the server may
#: still be opening or reading; it removes older ones it holds itself once their queries end)
KEEP_COPIES = 2
#: how often the publisher looks whether a copy is due, s
POLL_S = 0.05


@dataclass(frozen=True)
class SQLCopy:
    """One copy of the KD for SQL: ``path`` (its ``.wal`` beside it), ``cycle_t_ns`` (int64 ns
    of log time: the cycle whose flush it holds), ``serial`` (1, 2, ... per node),
    ``copy_ms`` (wall time the node's process spent copying, ms), ``file_bytes`` and
    ``wal_bytes`` (bytes copied)."""

    path: str
    cycle_t_ns: int
    serial: int
    copy_ms: float
    file_bytes: int
    wal_bytes: int


class NoCopyYet(ServeError):
    """No copy of the KD for SQL has been opened yet (the API answers 503 with Retry-After)."""


def flushed_cycle(live: Any) -> int | None:
    """The time (int64 ns of log time) of the newest cycle the KD file holds, as of the node's
    last flush: the last flush's cycle, or the newest cycle when the flush at the end of the
    log took everything (None before the first flush). Exact under the node's lock."""
    node, snap = live.node, live.snapshot
    flushed = node.flushed_t_ns if node is not None else None
    if flushed is None or snap is None:
        return None
    return min(int(flushed), snap.cycle_t_ns)


def _remove(path: str | Path) -> None:
    Path(path).unlink(missing_ok=True)
    Path(f"{path}.wal").unlink(missing_ok=True)


class CopyPublisher:
    """The node's process: copies the KD for the server's SQL while it is asked for (module
    docstring), posting each :class:`SQLCopy` to ``post``. ``live``: the node-side
    :class:`~wm.serve.LiveNode`; ``folder``: the server's; ``period_s``: at most one copy per
    this many s of wall time."""

    def __init__(
        self, live: Any, folder: str | Path, period_s: float, post: Callable[[SQLCopy], None]
    ) -> None:
        if not (math.isfinite(period_s) and period_s >= 0):
            raise ServeError(f"SQL copy period {period_s}: need a finite number >= 0 (s)")
        self.live, self.folder, self.period_s, self.post = live, Path(folder), period_s, post
        self.serial = 0
        self.failures = 0
        self._copied: list[str] = []
        self._last_key: tuple | None = None
        self._last_t = -math.inf
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="wm-sql-copy", daemon=True)

    def start(self) -> CopyPublisher:
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 10.0) -> None:
        """No copy after this returns (one under way is finished first)."""
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join(timeout_s)

    def _run(self) -> None:
        while not self._stop.wait(POLL_S):
            if SQL_KEY not in self.live.demand.wanted():
                continue
            if time.monotonic() - self._last_t < self.period_s:
                continue
            try:
                self.publish()
            except Exception as e:  # a copy that fails never stops the node; the next retries
                self.failures += 1
                log.warning("KD copy for SQL not made: %s", e)
                self._last_t = time.monotonic()

    def publish(self) -> SQLCopy | None:
        """Copy the KD now if a flush landed since the last copy (None: nothing new, or the
        node is not running). Takes the node's lock: between two cycles, no flush under way."""
        live = self.live
        with live.lock:
            if live.closed or live.kd is None or live.node is None:
                return None
            cycle = flushed_cycle(live)
            # the flush count tells a flush that added no cycle (the end of the log's) apart
            key = (cycle, live.node.stats.kd_flushes, live.status.done)
            if cycle is None or key == self._last_key:
                return None
            self.serial += 1
            path = self.folder / f"kd-{self.serial}.duckdb"
            t0 = time.perf_counter()
            file_bytes, wal_bytes = live.kd.copy_committed(path)
            copy_ms = 1e3 * (time.perf_counter() - t0)
        self._last_key, self._last_t = key, time.monotonic()
        self._copied.append(str(path))
        while len(self._copied) > KEEP_COPIES:  # a reader holding it open keeps its inode
            _remove(self._copied.pop(0))
        copy = SQLCopy(str(path), cycle, self.serial, copy_ms, file_bytes, wal_bytes)
        self.post(copy)
        return copy


class _Opened:
    """One copy open in the server's process, with the queries reading it now."""

    def __init__(self, copy: SQLCopy, con: Any, open_ms: float) -> None:
        self.copy, self.con, self.open_ms = copy, con, open_ms
        self.opened_t = time.monotonic()
        self.users = 0
        self.retired = False

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.con.close()
        _remove(self.copy.path)


class SQLCopies:
    """The server's process: the newest copy of the KD for SQL, opened read-only (module
    docstring). ``folder``: where the node's process writes the copies (removed with
    :meth:`close`)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._current: _Opened | None = None
        self._offered: SQLCopy | None = None
        self._closed = False
        self.copies_offered = 0
        self.copies_opened = 0
        self.open_failures = 0
        self.last_copy: SQLCopy | None = None  # the newest offered, opened or not
        self._thread = threading.Thread(target=self._open_loop, name="wm-sql-open", daemon=True)
        self._thread.start()

    def offer(self, copy: SQLCopy) -> None:
        """A new copy from the node (the news thread): opened next, unless a newer one comes
        first (that one is opened instead; the node removes the one passed over)."""
        with self._cond:
            self._offered, self.last_copy = copy, copy
            self.copies_offered += 1
            self._cond.notify()

    def _open_loop(self) -> None:
        from kd_store.query import open_copy

        while True:
            with self._cond:
                while self._offered is None and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                copy, self._offered = self._offered, None
            t0 = time.perf_counter()
            try:
                con = open_copy(copy.path)
            except Exception as e:  # removed already (a newer one passed it), or broken
                self.open_failures += 1
                log.warning("KD copy %s for SQL not opened: %s", copy.path, e)
                continue
            opened = _Opened(copy, con, 1e3 * (time.perf_counter() - t0))
            with self._lock:
                if self._closed:
                    opened.close()
                    return
                old, self._current = self._current, opened
                self.copies_opened += 1
                if old is not None:
                    old.retired = True
                    if old.users == 0:
                        old.close()

    def query(self, sql: str, limits: Any) -> tuple[pa.Table, SQLCopy]:
        """(Arrow table, the copy it read) of one read-only SELECT over the newest copy opened,
        within ``limits`` (:class:`kd_store.query.QueryLimits`: its time, row and byte
        limits). NoCopyYet before the first is open; KDError (or ResultTooLarge) as
        :func:`kd_store.query.query_reader` raises them."""
        from kd_store import persist
        from kd_store.query import SQLReader, query_reader

        with self._lock:
            cur = self._current
            if cur is None or self._closed:
                raise NoCopyYet(
                    "no read-only copy of the KD for SQL yet: SQL was asked for now, and the "
                    "node copies its KD after its next flush (about a second); retry shortly"
                )
            cur.users += 1
        try:
            reader = SQLReader(persist.cursor(cur.con))
            try:
                return query_reader(reader, sql, limits), cur.copy
            finally:
                reader.close()
        finally:
            with self._lock:
                cur.users -= 1
                if cur.retired and cur.users == 0:
                    cur.close()

    def figures(self, newest_cycle_t_ns: int) -> dict:
        """``sql`` of ``/v1/status``: the copy answers come from (its cycle, how far behind
        ``newest_cycle_t_ns`` and how old in wall time it is, the node's cost to copy it and
        the server's to open it) and the copies offered, opened and not opened."""
        with self._lock:
            cur = self._current
        out: dict[str, Any] = {
            "source": "copy", "copies_offered": self.copies_offered,
            "copies_opened": self.copies_opened, "open_failures": self.open_failures,
            "cycle_t_ns": None, "staleness_ns": None, "age_s": None, "copy_ms": None,
            "open_ms": None, "file_bytes": None, "wal_bytes": None,
        }  # fmt: skip
        if cur is not None:
            c = cur.copy
            out |= {
                "cycle_t_ns": c.cycle_t_ns,
                "staleness_ns": max(0, newest_cycle_t_ns - c.cycle_t_ns),
                "age_s": round(time.monotonic() - cur.opened_t, 3),
                "copy_ms": round(c.copy_ms, 3), "open_ms": round(cur.open_ms, 3),
                "file_bytes": c.file_bytes, "wal_bytes": c.wal_bytes,
            }  # fmt: skip
        return out

    def close(self) -> None:
        """Close every copy once its queries end and remove the folder (the node's process has
        stopped by then: nothing writes to it)."""
        with self._cond:
            self._closed = True
            cur, self._current = self._current, None
            self._cond.notify()
            if cur is not None:
                cur.retired = True
                if cur.users == 0:
                    cur.close()
        self._thread.join(10.0)
        shutil.rmtree(self.folder, ignore_errors=True)
