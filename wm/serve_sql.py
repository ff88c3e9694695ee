"""SQL of a live node answered outside the node, from a replica of its KD that each cycle's
changes keep current, so that no query costs the node anything but the changes it ships and
every answer is as of the newest cycle the server holds, or at most one cycle behind it.

DuckDB lets no other connection open a file one process writes, and copying the KD file on
every cycle would cost the node the whole file each time. Instead, while clients ask for SQL
(the demand key :data:`SQL_KEY`, held :data:`~wm.serve_copy.DEMAND_TTL_S` s after the last
ask), the node's side (:class:`ReplicaFeed`) ships the KD's changes:

* a seed (:class:`KDSeed`) when the feed starts, and again when the server asks for one: under
  the node's lock, between two cycles, the KD's changes since its last flush are collected
  (:meth:`~kd_store.store.KnowledgeDatabase.stage`), the KD file and its write-ahead log are
  copied to a new name in a folder of the server's (no CHECKPOINT, no fsync:
  :meth:`~kd_store.store.KnowledgeDatabase.copy_committed`) and the rows the file does not
  hold yet go with it (:attr:`~kd_store.store.KnowledgeDatabase.unflushed`): the copy with
  those rows written over it is the KD as of the newest cycle. At most one seed per
  :data:`SEED_PERIOD_S` s of wall time once the first is made.
* after every cycle, that cycle's changes (:class:`KDDelta`): the rows a flush at that cycle
  would write (:class:`kd_store.persist.Rows`: frames replaced by key, state rows appended,
  and the map tiles when the KD writes them), collected and converted to Arrow once
  (:meth:`~kd_store.store.KnowledgeDatabase.stage`). The KD holds them for its own flush (each
  second of log time), which writes them, merged, in one transaction: the file keeps its
  cadence and its cost. Numbered (``serial``), never dropped one by one: a server that falls
  behind by more than :data:`MAX_BEHIND_CYCLES` cycles has its backlog dropped and is
  reseeded from a fresh copy instead of holding an ever longer queue.

The server's side (:class:`SQLReplica`, a thread of its own) opens each seed as its own
database file, read-write for itself alone (the seed is the server's private copy: opening it
replays the log; no other process writes it), writes the seed's rows over it, then each
delta's rows in order (:func:`kd_store.persist.apply_rows`; deltas queued together merged into
one transaction), each commit with the cycle it brings the replica to. A delta out of order (a
gap: one the node dropped) stops the applying and asks the node for a new seed; the replica
answers meanwhile as of the last cycle it holds, and says so. A new seed replaces the replica
once open; the one before is closed and removed once its last query ends. When the node stops
feeding (SQL no longer asked for), the replica is closed: until a new seed is open, the node
answers SQL itself, from the KD as of its last flush (:func:`wm.serve.sql_query`).

Queries: each on a cursor of its own, in a transaction whose snapshot is taken together with
the cycle the replica holds (``cycle_t_ns``; no commit lands between the two), within the time,
row and byte limits (:func:`kd_store.query.query_reader`). The replica's connection is
configured as every untrusted query's (:func:`kd_store.query.sandbox_settings`: DuckDB's
external access off, its configuration locked, a memory and a thread limit); a statement is
one read-only SELECT, run in a transaction that is rolled back. With the node in a process of
its own, the server installs a cycle's snapshot once the replica has applied that cycle's delta
(waiting at most :data:`APPLY_WAIT_S` s), so that SQL answers are as of the same cycle as the
others (``staleness_ns`` 0) unless the replica falls behind; with the node in a thread, the
node never waits and a SQL answer may be one cycle behind while the newest delta is applied.

Costs: the node's process pays the collection and Arrow conversion of each cycle's changes
(the KD's flush pays that no more) and one copy of the file per seed; the server's process
pays the writes into the replica. ``/v1/status`` ``sql`` gives the replica's cycle and
staleness, the seeds (offered, opened, failed; the last one's copy and open times and bytes),
the deltas applied, dropped and out of order, and the time of the last and longest apply.
"""

from __future__ import annotations

import contextlib
import logging
import math
import shutil
import threading
import time
from collections import deque
from collections.abc import Callable, MutableSequence, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa

from wm.serve import ServeError

log = logging.getLogger(__name__)

#: the demand key a SQL request notes (:class:`wm.serve_copy.ServedDemand`)
SQL_KEY = "sql"
#: the node makes a seed (a copy of its KD file) at most this often once it made one, s of
#: wall time
SEED_PERIOD_S = 2.0
#: deltas (one per cycle) held for a server that has not applied them at most, in the node's
#: outbox and in the server's queue alike; beyond, they are dropped and the replica reseeded
MAX_BEHIND_CYCLES = 50
#: how long the server's news waits for the replica to apply a cycle's delta before it
#: installs that cycle's snapshot anyway, s (half a 10 Hz cycle)
APPLY_WAIT_S = 0.05
#: DuckDB worker threads of the replica (its writes and every query on it): a cycle's writes
#: and the small answers a server gives gain little from a second, which the node's cycle and
#: its odometry want on a machine of two cores
REPLICA_THREADS = 1
#: how often the node's feed looks whether SQL is asked for or a seed is due, s
POLL_S = 0.05
#: a seed due this long without a cycle's end (the node idle, or done) is made by the feed's
#: thread itself, s
IDLE_S = 0.5


@dataclass(frozen=True)
class KDDelta:
    """One cycle's changes of the KD: ``serial`` (1, 2, ... per node), ``cycle_t_ns`` (int64
    ns of log time: the KD with them is as of this cycle), ``rows`` (the cycle's
    :class:`kd_store.persist.Rows`, merged; None when nothing the file holds changed)."""

    serial: int
    cycle_t_ns: int
    rows: Any | None


@dataclass(frozen=True)
class KDSeed:
    """A copy of the KD to start a replica from: ``path`` (its ``.wal`` beside it; None: the
    node stopped feeding, the replica is closed), ``serial`` (the last delta it holds: the
    ones after it apply over it), ``cycle_t_ns`` (int64 ns of log time: the cycle it is as
    of), ``rows`` (the rows the file did not hold yet, merged: written over the copy; None:
    none), ``copy_ms`` (wall time the node spent copying, ms), ``file_bytes`` and
    ``wal_bytes`` (bytes copied)."""

    path: str | None
    serial: int
    cycle_t_ns: int
    rows: Any | None = None
    copy_ms: float = math.nan
    file_bytes: int = 0
    wal_bytes: int = 0


class NoReplicaYet(ServeError):
    """No replica of the KD for SQL is open (the API asks the node instead)."""


def flushed_cycle(live: Any) -> int | None:
    """The time (int64 ns of log time) of the newest cycle the KD file holds, as of the node's
    last flush: the last flush's cycle, or the newest cycle when the flush at the end of the
    log took everything (None before the first flush). Exact under the node's lock."""
    node, snap = live.node, live.snapshot
    flushed = node.flushed_t_ns if node is not None else None
    if flushed is None or snap is None:
        return None
    return min(int(flushed), snap.cycle_t_ns)


def drop_backlog(items: MutableSequence[KDDelta | KDSeed], max_behind: int) -> int:
    """The one rule of a backlog, in the node's outbox and the server's queue alike: when
    ``items`` (in order) hold more than ``max_behind`` deltas, they are all dropped (in
    place; the seeds stay) and their number returned, for a new seed to replace them;
    else 0."""
    deltas = sum(isinstance(i, KDDelta) for i in items)
    if deltas <= max_behind:
        return 0
    seeds = [i for i in items if isinstance(i, KDSeed)]
    items.clear()
    items.extend(seeds)
    return deltas


def _remove(path: str | Path) -> None:
    Path(path).unlink(missing_ok=True)
    Path(f"{path}.wal").unlink(missing_ok=True)


def _merged(rows: Sequence[Any]) -> Any | None:
    from kd_store import persist

    merged = persist.merge_rows(rows)
    return merged if merged else None


# --- the node's side ---------------------------------------------------------------------------


class ReplicaFeed:
    """The node's side (module docstring): while SQL is asked for, a :class:`KDSeed` when the
    feed starts and when asked (:meth:`reseed`), and a :class:`KDDelta` after every cycle
    (:meth:`cycle_end`), each handed to ``post`` in order. ``live``: the node-side
    :class:`~wm.serve.LiveNode`; ``folder``: the server's, where seeds are copied to (the
    server owns and removes them); ``seed_period_s``: at most one seed per this many s of
    wall time after the first.

    A thread of its own decides when a seed is due (or the feed ends: SQL no longer asked
    for); the node's thread makes it at the end of its next cycle, where it holds the node's
    lock already (a thread waiting for that lock while the node runs cycles back to back
    may wait long). A node that runs no cycle for :data:`IDLE_S` s (done with its log, or
    fed nothing) has it made by that thread, under the node's lock."""

    def __init__(
        self,
        live: Any,
        folder: str | Path,
        post: Callable[[KDDelta | KDSeed], None],
        seed_period_s: float = SEED_PERIOD_S,
    ) -> None:
        if not (math.isfinite(seed_period_s) and seed_period_s >= 0):
            raise ServeError(f"SQL seed period {seed_period_s}: need a finite number >= 0 (s)")
        self.live, self.folder, self.post = live, Path(folder), post
        self.seed_period_s = seed_period_s
        self.feeding = False
        self.serial = 0  # of the last delta posted
        self.seeds = 0
        self.failures = 0
        self._rows: list[Any] = []  # rows the KD collected since the last delta
        self._cycle_t_ns = -1  # of the last delta or seed
        self._reseed = threading.Event()
        self._due: str | None = None  # "seed" or "halt", for the node's next cycle end
        self._due_t = 0.0
        self._last_seed_t = -math.inf
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="wm-sql-feed", daemon=True)

    def start(self) -> ReplicaFeed:
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 10.0) -> None:
        """No seed after this returns (one under way is finished first); the deltas go on
        while the node runs, so that its last changes reach the replica too."""
        self._stop.set()
        self._due = None
        if self._thread.ident is not None:
            self._thread.join(timeout_s)

    def reseed(self) -> None:
        """Make a new seed as soon as the period allows (the server's replica fell behind,
        or deltas were dropped on their way)."""
        self._reseed.set()

    def _collect(self, rows: Any) -> None:
        """The KD's :attr:`~kd_store.store.KnowledgeDatabase.on_rows`, under the node's lock."""
        self._rows.append(rows)

    def cycle_end(self, cycle_t_ns: int, ran: bool = True) -> None:
        """The node's thread, under the node's lock, after each step fed (a frame, the end):
        when feeding and the step ran a cycle (``ran``) or the KD wrote rows meanwhile, the
        changes since the last delta as the next one; a seed or the feed's end when due.
        ``cycle_t_ns``: the newest cycle's time (int64 ns of log time; -1 before any). A step
        that ran no cycle is not collected on its own (most frames are not sweeps): what it
        changed goes with the next cycle's changes."""
        if self._due is not None:
            self._do_due()
        if not self.feeding or not (ran or self._rows):
            return
        self.live.kd.stage()
        rows, self._rows = self._rows, []
        if not rows and cycle_t_ns == self._cycle_t_ns:
            return  # nothing new: no frame of a cycle
        self.serial += 1
        self._cycle_t_ns = cycle_t_ns
        self.post(KDDelta(self.serial, cycle_t_ns, _merged(rows)))

    def _run(self) -> None:
        while not self._stop.wait(POLL_S):
            if self._due is not None:
                if time.monotonic() - self._due_t >= IDLE_S:  # no cycle end came: idle
                    with self.live.lock:
                        self._do_due()
                continue
            wanted = SQL_KEY in self.live.demand.wanted()
            if wanted and (not self.feeding or self._reseed.is_set()):
                if time.monotonic() - self._last_seed_t >= self.seed_period_s:
                    self._due_t, self._due = time.monotonic(), "seed"
            elif not wanted and self.feeding:
                self._due_t, self._due = time.monotonic(), "halt"

    def _do_due(self) -> None:
        """Make the seed, or end the feed, that is due; under the node's lock."""
        due, self._due = self._due, None
        if due == "halt":
            self._halt()
        elif due == "seed":
            try:
                if self._seed() is None:
                    return  # nothing to seed from yet: asked again at the next poll
            except Exception as e:  # a seed that fails never stops the node; the next retries
                self.failures += 1
                log.warning("KD seed for SQL not made: %s", e)
            self._last_seed_t = time.monotonic()

    def _seed(self) -> KDSeed | None:
        """Start (or restart) the feed with a seed (None: the node is not running, or ran no
        cycle yet: the feed thread asks again). Under the node's lock: between two cycles,
        no flush under way."""
        live = self.live
        if live.closed or live.kd is None or live.node is None or live.snapshot is None:
            return None
        self._reseed.clear()
        kd = live.kd
        kd.on_rows = self._collect
        self.feeding = True
        kd.stage()  # the changes since the last flush: with the file, the newest cycle
        self._rows = []  # in the seed, not in a delta
        path = self.folder / f"kd-{self.seeds + 1}.duckdb"
        t0 = time.perf_counter()
        file_bytes, wal_bytes = kd.copy_committed(path)
        copy_ms = 1e3 * (time.perf_counter() - t0)
        self.seeds += 1
        self._cycle_t_ns = live.snapshot.cycle_t_ns
        seed = KDSeed(str(path), self.serial, self._cycle_t_ns, _merged(kd.unflushed),
                      copy_ms, file_bytes, wal_bytes)  # fmt: skip
        self.post(seed)
        return seed

    def _halt(self) -> None:
        """Stop feeding (SQL no longer asked for): the server closes its replica."""
        if self.live.kd is not None:
            self.live.kd.on_rows = None
        self.feeding = False
        self._rows = []
        self.post(KDSeed(None, self.serial, self._cycle_t_ns))


# --- the server's side -------------------------------------------------------------------------


class _Replica:
    """One replica open in the server's process: its connection, the last delta it holds
    (``serial``) and the cycle it is as of, and the queries reading it now."""

    def __init__(self, seed: KDSeed, con: Any, open_ms: float) -> None:
        from kd_store import persist

        self.seed, self.con, self.open_ms = seed, con, open_ms
        # the applying thread's own cursor: ``con`` only hands out the queries' cursors, one
        # at a time (a DuckDB connection is used by one thread at a time)
        self.writer = persist.cursor(con)
        self._cursor_lock = threading.Lock()
        self.serial, self.cycle_t_ns = seed.serial, seed.cycle_t_ns
        self.commit_lock = threading.Lock()  # a commit and the cycle it brings, together
        self.users = 0
        self.retired = False

    def cursor(self) -> Any:
        """A cursor of its own for one query."""
        from kd_store import persist

        with self._cursor_lock:
            return persist.cursor(self.con)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.writer.close()
        with contextlib.suppress(Exception):
            self.con.close()
        if self.seed.path is not None:
            _remove(self.seed.path)


class SQLReplica:
    """The server's side (module docstring): a replica of the KD, kept current from the
    seeds and deltas :meth:`offer` is given, queried with :meth:`query`. ``folder``: where
    the node writes the seeds (removed with :meth:`close`); ``request_seed``: asks the node
    for a new seed (the replica fell behind or lost a delta); ``max_behind``: deltas queued
    at most before the backlog is dropped and a seed asked for; ``limits``: the memory and
    thread limits of the replica's connection (:class:`kd_store.query.QueryLimits`; default:
    :data:`REPLICA_THREADS` threads)."""

    def __init__(
        self,
        folder: str | Path,
        request_seed: Callable[[], None],
        max_behind: int = MAX_BEHIND_CYCLES,
        limits: Any | None = None,
    ) -> None:
        from kd_store.query import QueryLimits

        self.folder = Path(folder)
        self.request_seed = request_seed
        self.max_behind = max_behind
        self.limits = limits if limits is not None else QueryLimits(threads=REPLICA_THREADS)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._queue: deque[KDDelta | KDSeed] = deque()
        self._busy = False  # the thread applies what it took from the queue
        self._seeding = False  # ... and that is a seed being opened
        self._current: _Replica | None = None
        self._gap = False  # a delta is missing: nothing applies until the next seed
        self._closed = False
        self.seeds_offered = 0
        self.seeds_opened = 0
        self.seed_failures = 0
        self.deltas_applied = 0
        self.deltas_dropped = 0  # queued beyond ``max_behind``, or after a gap
        self.gaps = 0
        self.seeds_asked = 0
        self.apply_ms = math.nan  # the last apply's wall time, ms
        self.apply_ms_max = 0.0
        self.last_seed: KDSeed | None = None  # the newest offered, opened or not
        self._thread = threading.Thread(target=self._run, name="wm-sql-replica", daemon=True)
        self._thread.start()

    # --- what the node sends ---------------------------------------------------------------

    def offer(self, items: Sequence[KDDelta | KDSeed]) -> None:
        """Seeds and deltas from the node, in the order it made them (the news thread, or
        the node's own thread: never waits). A seed supersedes everything queued before it;
        a queue of more than ``max_behind`` deltas is dropped and a seed asked for."""
        ask = False
        with self._cond:
            if self._closed:
                return
            for item in items:
                if isinstance(item, KDSeed):
                    for old in self._queue:  # passed over: the seed holds what they did
                        if isinstance(old, KDSeed) and old.path is not None:
                            _remove(old.path)
                    self._queue.clear()
                    if item.path is not None:
                        self.seeds_offered += 1
                        self.last_seed = item
                self._queue.append(item)
            dropped = drop_backlog(self._queue, self.max_behind)
            if dropped:
                self.deltas_dropped += dropped
                self._gap = ask = True
            self._cond.notify_all()
        if ask:
            self._ask_seed()

    def wait_applied(self, timeout_s: float) -> bool:
        """Wait until what was offered is applied (at most ``timeout_s`` s); whether it is.
        Returns at once while no replica is open, or one is being seeded, or it lost a delta:
        nothing would be as of the newest cycle sooner by waiting."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._queue or self._busy:
                if self._current is None or self._gap or self._seeding:
                    return False
                if any(isinstance(i, KDSeed) for i in self._queue):
                    return False
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def _ask_seed(self) -> None:
        self.seeds_asked += 1
        try:
            self.request_seed()
        except Exception as e:  # the node is gone: its end is reported elsewhere
            log.warning("new KD seed for SQL not asked for: %s", e)

    # --- the thread that applies ------------------------------------------------------------

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                if isinstance(self._queue[0], KDSeed):
                    batch: list = [self._queue.popleft()]
                    self._seeding = True
                else:  # every delta up to the next seed: one transaction
                    batch = []
                    while self._queue and isinstance(self._queue[0], KDDelta):
                        batch.append(self._queue.popleft())
                self._busy = True
            try:
                if isinstance(batch[0], KDSeed):
                    self._open(batch[0])
                else:
                    self._apply(batch)
            except Exception as e:  # the replica no longer follows the node: a new seed
                log.warning("SQL replica: %s; asking for a new seed", e)
                with self._lock:
                    self._gap = True
                self._ask_seed()
            finally:
                with self._cond:
                    self._busy = self._seeding = False
                    self._cond.notify_all()

    def _open(self, seed: KDSeed) -> None:
        """Open ``seed`` as the replica (None path: close the replica)."""
        from kd_store import persist
        from kd_store.query import sandbox_settings

        opened = None
        if seed.path is not None:
            t0 = time.perf_counter()
            con = None
            try:
                # the server's own copy, written by this thread alone: read-write
                con = persist.connect(seed.path, settings=sandbox_settings(self.limits))
                if seed.rows is not None:
                    persist.write_rows(con, seed.rows)
            except Exception as e:  # broken: the next seed replaces it
                self.seed_failures += 1
                if con is not None:
                    with contextlib.suppress(Exception):
                        con.close()
                _remove(seed.path)
                raise ServeError(f"seed {seed.path} not opened ({e})") from None
            opened = _Replica(seed, con, 1e3 * (time.perf_counter() - t0))
        with self._lock:
            if self._closed:
                if opened is not None:
                    opened.close()
                return
            old, self._current = self._current, opened
            self._gap = False
            self.seeds_opened += opened is not None
        if old is not None:
            self._retire(old)

    def _apply(self, deltas: list[KDDelta]) -> None:
        """Write the rows of ``deltas`` (in order, numbered on from the replica's) in one
        transaction; a gap in the numbers stops there and asks for a seed."""
        from kd_store import persist

        cur = self._current
        if cur is None or self._gap:
            self.deltas_dropped += len(deltas)
            return
        fresh = [d for d in deltas if d.serial > cur.serial]  # older ones: in the seed
        run: list[KDDelta] = []
        for d in fresh:
            if d.serial != cur.serial + len(run) + 1:
                break
            run.append(d)
        if run:
            t0 = time.perf_counter()
            rows = persist.merge_rows([d.rows for d in run if d.rows is not None])
            if rows:
                cur.writer.execute("BEGIN TRANSACTION")
                try:
                    persist.apply_rows(cur.writer, rows)
                except BaseException:
                    cur.writer.execute("ROLLBACK")
                    raise
            with cur.commit_lock:  # the cycle a query reads with its snapshot
                if rows:
                    cur.writer.execute("COMMIT")
                cur.serial, cur.cycle_t_ns = run[-1].serial, run[-1].cycle_t_ns
            self.apply_ms = 1e3 * (time.perf_counter() - t0)
            self.apply_ms_max = max(self.apply_ms_max, self.apply_ms)
            self.deltas_applied += len(run)
        if len(run) < len(fresh):
            self.gaps += 1
            self.deltas_dropped += len(fresh) - len(run)
            with self._lock:
                self._gap = True
            self._ask_seed()

    def _retire(self, r: _Replica) -> None:
        with self._lock:
            r.retired = True
            done = r.users == 0
        if done:
            r.close()

    # --- queries ---------------------------------------------------------------------------

    def query(self, sql: str, limits: Any) -> tuple[pa.Table, int]:
        """(Arrow table, the cycle it is as of: int64 ns of log time) of one read-only SELECT
        over the replica, within ``limits`` (:class:`kd_store.query.QueryLimits`: its time,
        row and byte limits). NoReplicaYet while none is open; KDError (or ResultTooLarge)
        as :func:`kd_store.query.query_reader` raises them."""
        from kd_store.query import SQLReader, query_reader

        with self._lock:
            cur = self._current
            if cur is None or self._closed:
                raise NoReplicaYet(
                    "no replica of the KD for SQL yet: the node sends a copy of its KD within a "
                    "few tenths of a second of the first SQL request"
                )
            cur.users += 1
        try:
            reader = SQLReader(cur.cursor())
            try:
                with reader.snapshot():
                    with cur.commit_lock:  # the snapshot is taken at the first read
                        reader.sql("SELECT count(*) FROM kd_meta")
                        cycle = cur.cycle_t_ns
                    return query_reader(reader, sql, limits), cycle
            finally:
                reader.close()
        finally:
            with self._lock:
                cur.users -= 1
                done = cur.retired and cur.users == 0
            if done:
                cur.close()

    def figures(self, newest_cycle_t_ns: int) -> dict:
        """``sql`` of ``/v1/status``: the replica answers come from (the cycle it is as of,
        how far that is behind ``newest_cycle_t_ns``), the seeds (offered, opened, failed,
        asked for; the last one's copy time and bytes in the node, its open time here), the
        deltas (applied, dropped, gaps) and the applies' wall time (the last, the longest)."""

        def ms(v: float) -> float | None:
            return None if v != v else round(v, 3)  # NaN: none yet

        with self._lock:
            cur = self._current
            queued = sum(isinstance(i, KDDelta) for i in self._queue)
        seed = self.last_seed
        out: dict[str, Any] = {
            "source": "replica", "cycle_t_ns": None, "staleness_ns": None,
            "seeds_offered": self.seeds_offered, "seeds_opened": self.seeds_opened,
            "seed_failures": self.seed_failures, "seeds_asked": self.seeds_asked,
            "deltas_applied": self.deltas_applied, "deltas_queued": queued,
            "deltas_dropped": self.deltas_dropped, "gaps": self.gaps,
            "apply_ms": ms(self.apply_ms), "apply_ms_max": round(self.apply_ms_max, 3),
            "copy_ms": ms(seed.copy_ms) if seed is not None else None,
            "file_bytes": seed.file_bytes if seed is not None else None,
            "wal_bytes": seed.wal_bytes if seed is not None else None,
            "open_ms": round(cur.open_ms, 3) if cur is not None else None,
        }  # fmt: skip
        if cur is not None:
            out["cycle_t_ns"] = cur.cycle_t_ns
            out["staleness_ns"] = max(0, newest_cycle_t_ns - cur.cycle_t_ns)
        return out

    def close(self) -> None:
        """Close the replica once its queries end and remove the folder (the node has stopped
        by then: nothing writes to it)."""
        with self._cond:
            self._closed = True
            cur, self._current = self._current, None
            for item in self._queue:
                if isinstance(item, KDSeed) and item.path is not None:
                    _remove(item.path)
            self._queue.clear()
            self._cond.notify_all()
        self._thread.join(10.0)
        if cur is not None:
            self._retire(cur)
        shutil.rmtree(self.folder, ignore_errors=True)
