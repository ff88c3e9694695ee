"""The live node in a process of its own (``LiveNode(..., process=True)``, the default of
``wm serve``), so that the server's Python work never takes the node's interpreter lock: with
both in one process they take turns on it, and the node's cycles grow with the request rate.

The node's process (spawned: :func:`_node_main`) builds the same :class:`~wm.serve.LiveNode`
(or :class:`~wm.ingest.IngestNode`) it would build in a thread, owns the KD file and the
:class:`~wm.node.WorldModelNode`, and runs the replay (or the ingest) loop. The server's
process keeps a :class:`NodeLink` to it over two pipes:

* news (node -> server, one way): after each frame fed, the node posts its
  :class:`~wm.serve.LiveStatus` and, after a cycle, the cycle's
  :class:`~wm.serve.CycleSnapshot` to an :class:`_Outbox`; a sender thread sends what is there
  as one message, pickled (protocol 5) with the arrays of 64 kB and more out of band, each
  written to the pipe as it lies in memory. The node never waits for the server: a snapshot
  the server has not taken yet is replaced by the newer one (latest wins) and counted
  (``replaced``). A status without a new snapshot goes at most every
  :data:`STATUS_PERIOD_S` s; the last one (the node done) at once. The server installs each
  snapshot for the answers that read it without the node (``LiveNode.snapshot``) and hands the
  stream's messages to its feed.
* requests (both ways): ``LiveNode.call(fn, *args)`` sends a module-level function by name and
  its arguments; a pool of :data:`CALL_THREADS` threads in the node's process runs
  ``fn(node_side_live, *args)`` (taking the node's lock where ``fn`` reads the node) and sends
  back the answer or the exception (an HTTPException as its status and detail). The server also
  tells the node, without an answer: the views clients asked for lately
  (:class:`~wm.serve_copy.ServedDemand`; at once when a key is new, else after each snapshot
  when the list changed), and how many stream clients there are.
* SQL (a KD file only): while clients ask for it, the news carries a seed of a replica of the
  KD (a copy of the file, when the feed starts and when the server asks: ``sql_seed``) and
  each cycle's changes of the KD after it, in order and never replaced by newer ones (at most
  :data:`~wm.serve_sql.MAX_BEHIND_CYCLES` held; beyond, they are dropped and the replica
  reseeded); the server keeps its replica current with them and answers SQL from it itself,
  costing the node's process only the changes and the seeds (:mod:`wm.serve_sql`). The server
  installs a cycle's snapshot once its replica holds that cycle's changes (waiting at most
  :data:`~wm.serve_sql.APPLY_WAIT_S` s).

Frames posted to ``/v1/ingest`` are decoded in the server's process and cross in a bounded
:class:`multiprocessing.Queue` (full: dropped and counted, :mod:`wm.ingest`).

A stop (``LiveNode.stop``; also SIGTERM sent to the node's process, e.g. by a service manager
that signals the whole group) ends the replay, finishes the node and flushes and closes the
KD before the process exits; SIGINT (Ctrl-C to the terminal's group) is left to the server's
process, which stops the node so. The node's process dies with the server's
(:func:`core.process.die_with_parent`, and a thread watching the parent's pid). A node process
that dies is seen at once (the end of its pipes): ``/v1/status`` names it in ``error``, the
snapshot is dropped, and every answer that needs the node is a 503, a request in flight
included; a request the node does not answer within its timeout is a 503 too.

Figures (``/v1/status``, ``node_process``): ``transfer_ms``, wall time from the node's post of
a snapshot to its install in the server (pickling, the pipe, unpickling, and the wait for the
sender while it sent the one before); ``send_ms``, the node's process's share (pickling and
writing), which is what the transfer costs the node; ``replaced``, snapshots replaced before
the server took them; ``replica_dropped``, cycles' changes of the KD dropped before they were
sent (the server fell behind: its replica is reseeded). ``transfer_ms`` includes the wait
for the replica to apply the cycle's changes while SQL is served.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import fcntl
import itertools
import multiprocessing as mp
import os
import pickle
import queue
import signal
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Hashable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from fastapi import HTTPException

from core.process import die_with_parent, exit_with_parent
from wm.serve import CycleSnapshot, LiveNode, LiveStatus, ServeError
from wm.serve_sql import (
    APPLY_WAIT_S,
    MAX_BEHIND_CYCLES,
    KDDelta,
    KDSeed,
    ReplicaFeed,
    drop_backlog,
)

#: threads in the node's process answering requests (SQL may take seconds: more than one)
CALL_THREADS = 4
#: a status without a new snapshot is sent at most this often, s
STATUS_PERIOD_S = 0.05
#: arrays smaller than this are pickled in band: a write per buffer costs more than a copy
OUT_OF_BAND_BYTES = 64 * 1024
#: stream messages held for the server at most (a server that takes none for this many
#: cycles has stalled); older ones are dropped and counted
STREAM_BACKLOG = 256
#: the news pipe's kernel buffer (Linux; 1 MiB is the default most an unprivileged process
#: may ask for): a snapshot of a few MB crosses in a few writes, not one per 64 kB
NEWS_PIPE_BYTES = 2**20
_COUNT = struct.Struct("<I")


# --- framed messages: pickle protocol 5 with out-of-band buffers ------------------------------


def send_message(conn: Any, obj: Any, lock: threading.Lock) -> None:
    """Send ``obj`` on ``conn`` (a :class:`multiprocessing.connection.Connection`): a head
    (buffer count and sizes, then the pickle) as one message, then each large contiguous
    array's bytes written to the descriptor as they lie in memory; ``lock`` keeps one sender's
    parts together."""
    buffers: list[pickle.PickleBuffer] = []

    def out_of_band(buf: pickle.PickleBuffer) -> bool:
        if buf.raw().nbytes < OUT_OF_BAND_BYTES:
            return True  # in band
        buffers.append(buf)
        return False

    body = pickle.dumps(obj, protocol=5, buffer_callback=out_of_band)
    raws = [b.raw() for b in buffers]
    head = _COUNT.pack(len(raws)) + struct.pack(f"<{len(raws)}Q", *(r.nbytes for r in raws))
    with lock:
        conn.send_bytes(head + body)
        fd = conn.fileno()
        for raw in raws:
            sent = 0
            while sent < raw.nbytes:  # the interpreter lock is free while the kernel copies
                sent += os.write(fd, raw[sent:])


def recv_message(conn: Any) -> Any:
    """The next object :func:`send_message` sent on ``conn``; its large arrays are read from
    the descriptor straight into buffers of their own (writable). EOFError when the other end
    is closed."""
    head = conn.recv_bytes()
    (n,) = _COUNT.unpack_from(head)
    sizes = struct.unpack_from(f"<{n}Q", head, _COUNT.size)
    fd = conn.fileno()
    buffers = []
    for size in sizes:
        buf = np.empty(size, np.uint8)
        view, got = memoryview(buf), 0
        while got < size:
            k = os.readv(fd, [view[got:]])
            if k == 0:
                raise EOFError("the other end closed mid-message")
            got += k
        buffers.append(buf)
    return pickle.loads(memoryview(head)[_COUNT.size + 8 * n :], buffers=buffers)


# --- the node's process ------------------------------------------------------------------------


@dataclass
class NodeNews:
    """One message of the news pipe: the node's status and the newest cycle's snapshot (each
    None: none since the last message), the stream's messages since, and the outbox's
    figures."""

    status: LiveStatus | None
    snapshot: CycleSnapshot | None
    posted_t: float  # time.monotonic() when the snapshot was posted (the clock is the host's)
    stream: list[bytes] = field(default_factory=list)
    replaced: int = 0  # snapshots replaced before they were sent, since the start
    stream_dropped: int = 0
    send_ms: float = float("nan")  # the node's process's pickling and writing of the last one
    final: bool = False
    # seeds and deltas of the server's replica of the KD for SQL since the last message, in
    # the order they were made (wm.serve_sql)
    replica: list[KDDelta | KDSeed] = field(default_factory=list)
    replica_dropped: int = 0  # deltas dropped before they were sent, since the start


class _Outbox:
    """What the node's thread posts for the server: one slot for the newest snapshot (a newer
    one replaces it, counted), the newest status, the stream's messages, the replica's seeds
    and deltas (all kept, in order, at most :data:`~wm.serve_sql.MAX_BEHIND_CYCLES` deltas:
    beyond, the deltas are dropped, counted, and ``on_replica_dropped`` is called, so that
    the feed makes a new seed). The sender thread takes it all at once."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._status: LiveStatus | None = None
        self._snapshot: CycleSnapshot | None = None
        self._posted_t = 0.0
        self._stream: deque[bytes] = deque()
        self._final = False
        self._replica: list[KDDelta | KDSeed] = []
        self._closed = False
        self.replaced = 0
        self.stream_dropped = 0
        self.replica_dropped = 0
        self.on_replica_dropped: Callable[[], None] | None = None

    def post(self, live: LiveNode, fresh: bool, final: bool) -> None:
        """The node's thread, after a frame: its status and, when ``fresh``, its snapshot."""
        status = dataclasses.replace(live.status)  # the node's thread goes on writing its own
        with self._cond:
            self._status = status
            if fresh and live.snapshot is not None:
                self.replaced += self._snapshot is not None
                self._snapshot, self._posted_t = live.snapshot, time.monotonic()
            self._final |= final
            self._cond.notify()

    def post_replica(self, item: KDDelta | KDSeed) -> None:
        """The replica's feed (:class:`~wm.serve_sql.ReplicaFeed`), under the node's lock: a
        seed, or a cycle's delta. A delta wakes no sender: the node's thread posts the cycle's
        status right after, and both go in one message."""
        with self._cond:
            self._replica.append(item)
            # the server far behind: its deltas dropped, a new seed instead
            dropped = drop_backlog(self._replica, MAX_BEHIND_CYCLES)
            self.replica_dropped += dropped
            if isinstance(item, KDSeed):
                self._cond.notify()
        if dropped and self.on_replica_dropped is not None:
            self.on_replica_dropped()

    def stream(self, message: bytes) -> None:
        with self._cond:
            if len(self._stream) >= STREAM_BACKLOG:
                self._stream.popleft()
                self.stream_dropped += 1
            self._stream.append(message)
            self._cond.notify()

    def close(self) -> None:
        """Nothing more will be posted: :meth:`take` returns None once all is taken."""
        with self._cond:
            self._closed = True
            self._cond.notify()

    def take(self, last_sent: float, send_ms: float) -> NodeNews | None:
        """The news to send: waits until there is a snapshot, stream messages, a seed or
        delta of the replica or the final status, or a status and :data:`STATUS_PERIOD_S` s
        since ``last_sent``; None when closed (:meth:`close`) with nothing left to send."""
        with self._cond:
            while True:
                urgent = self._snapshot is not None or self._stream or self._final
                urgent = urgent or bool(self._replica)
                wait = last_sent + STATUS_PERIOD_S - time.monotonic()
                if urgent or (self._status is not None and (wait <= 0 or self._closed)):
                    break
                if self._closed:
                    return None
                self._cond.wait(wait if self._status is not None else None)
            news = NodeNews(
                self._status, self._snapshot, self._posted_t,
                list(self._stream), self.replaced, self.stream_dropped, send_ms, self._final,
                self._replica, self.replica_dropped,
            )  # fmt: skip
            self._status, self._snapshot, self._replica = None, None, []
            self._stream.clear()
            self._final = False  # sent: the news after (seeds for SQL) are no final ones
            return news


def _send_news(outbox: _Outbox, conn: Any) -> None:
    """The sender thread of the node's process: news until the outbox is closed (the node
    stopped; a node done with its log still sends seeds of its KD for SQL), or until the
    server's end of the pipe is closed."""
    lock = threading.Lock()
    last, send_ms = 0.0, float("nan")
    while True:
        news = outbox.take(last, send_ms)
        if news is None:
            return
        t = time.perf_counter()
        try:
            send_message(conn, news, lock)
        except OSError:  # the server's process is gone: nobody to tell
            return
        last, send_ms = time.monotonic(), 1e3 * (time.perf_counter() - t)


class _GivenDemand:
    """The views the server's clients asked for lately, as the server last told (most
    recently asked first): what the node's cycles copy (:meth:`wanted`)."""

    def __init__(self) -> None:
        self._wanted: list[Hashable] = []

    def set(self, wanted: list[Hashable]) -> None:
        self._wanted = list(wanted)

    def wanted(self) -> list[Hashable]:
        return self._wanted

    def ask(self, keys: Any) -> None:  # the server's process notes what is asked
        pass


def _raise_stop(signum: int, frame: Any) -> None:
    """SIGTERM in the node's process: stop as the server would stop it. SystemExit, like the
    interpreter's own, passes every ``except Exception`` on its way to the loop's end."""
    raise SystemExit(0)


def _answer(live: LiveNode, conn: Any, lock: threading.Lock, ident: int, fn, args) -> None:
    """Run one request and send its answer: ("ok", value), ("http", (status, detail)) or
    ("error", exception); an exception that does not pickle goes as a ServeError naming it."""
    try:
        reply: tuple = ("ok", fn(live, *args))
    except HTTPException as e:
        reply = ("http", (e.status_code, e.detail))
    except Exception as e:
        try:
            pickle.dumps(e)
            reply = ("error", e)
        except Exception:
            reply = ("error", ServeError(f"{type(e).__name__}: {e}"))
    try:
        send_message(conn, ("reply", ident, reply), lock)
    except OSError:
        pass  # the server's process is gone
    except Exception as e:  # an answer that does not pickle
        err = ServeError(f"the answer of {getattr(fn, '__name__', fn)} could not be sent: {e}")
        with contextlib.suppress(OSError):
            send_message(conn, ("reply", ident, ("error", err)), lock)


def _call_worker(live: LiveNode, calls: queue.Queue, conn: Any, lock: threading.Lock) -> None:
    while True:
        ident, fn, args = calls.get()
        _answer(live, conn, lock, ident, fn, args)


def _node_main(
    cls: type,
    kwargs: dict[str, Any],
    ingest_queue: Any,
    news_conn: Any,
    request_conn: Any,
    parent: int,
    start_timeout_s: float,
    sql_feed: tuple[str, float] | None = None,
) -> None:
    """The node's process: build and start the node, tell the server it is ready (or why
    not), answer requests until told to stop (or SIGTERM), then stop the node (the KD
    flushed and closed) and send the final status. ``sql_feed``: (the server's folder for
    the seeds of its replica of the KD for SQL, the least time between two seeds in s of wall
    time), None: SQL goes to the node."""
    die_with_parent(parent)
    exit_with_parent(parent, "wm-node-watch")  # where prctl is not there (or not allowed)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server's process stops the node
    signal.signal(signal.SIGTERM, _raise_stop)
    reply_lock = threading.Lock()
    outbox = _Outbox()
    live: LiveNode | None = None
    feed: ReplicaFeed | None = None
    try:
        live = cls(**kwargs)
        live.local_sql = False  # the server's process answers SQL (or sends it here)
        if ingest_queue is not None:
            live.queue = ingest_queue
        live.demand = _GivenDemand()  # type: ignore[assignment]
        live.on_publish = lambda fresh, final: outbox.post(live, fresh, final)
        live.stream_sink = outbox.stream
        sender = threading.Thread(target=_send_news, args=(outbox, news_conn),
                                  name="wm-node-news", daemon=True)  # fmt: skip
        sender.start()
        live.start(start_timeout_s)
        info = {"vj_config": live.vj_config, "levels": live.map_levels, "pid": os.getpid()}
        if sql_feed is not None:
            feed = ReplicaFeed(live, sql_feed[0], outbox.post_replica, sql_feed[1])
            outbox.on_replica_dropped = feed.reseed
            live.kd_feed = feed
            feed.start()
        send_message(request_conn, ("ready", info, ""), reply_lock)
        calls: queue.Queue = queue.Queue()
        for k in range(CALL_THREADS):
            threading.Thread(target=_call_worker, args=(live, calls, request_conn, reply_lock),
                             name=f"wm-node-call-{k}", daemon=True).start()  # fmt: skip
        while True:
            try:
                kind, *rest = recv_message(request_conn)
            except (EOFError, OSError):  # the server's process is gone
                break
            if kind == "call":
                calls.put(tuple(rest))
            elif kind == "demand":
                live.demand.set(rest[0])  # type: ignore[attr-defined]
            elif kind == "stream_clients":
                live.stream_clients = int(rest[0])
            elif kind == "sql_seed" and feed is not None:
                feed.reseed()
            elif kind == "stop":
                break
    except SystemExit:
        pass
    except Exception as e:
        if live is None or live.node is None:  # it did not start: say why, as a thread would
            why = live.status.error if live is not None and live.status.error else None
            why = why or f"{type(e).__name__}: {e}"
            with contextlib.suppress(OSError):
                send_message(request_conn, ("ready", None, why), reply_lock)
            return
        live.status.error = live.status.error or f"{type(e).__name__}: {e}"
    # a second SIGTERM while the KD is flushed must not cut the flush short
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if feed is not None:  # no seed of a KD being closed (its last changes still go out)
        feed.stop()
    if live is not None:
        live.stop()
        outbox.post(live, False, True)  # the final status, whatever the replay had sent
        outbox.close()
        sender.join(10.0)
    if ingest_queue is not None:  # frames the node did not take must not hold up the exit
        ingest_queue.cancel_join_thread()
    with contextlib.suppress(OSError):
        send_message(request_conn, ("stopped",), reply_lock)


# --- the server's process ----------------------------------------------------------------------


class NodeLink:
    """The server's side of a node in a process of its own (module docstring): starts and
    stops the process, installs what it sends into the :class:`~wm.serve.LiveNode` ``live``
    (``snapshot``, ``status``, the stream), sends it requests (:meth:`call`) and the demand."""

    def __init__(self, live: LiveNode) -> None:
        self.live = live
        self.info: dict[str, Any] = {}
        self.alive = False
        self.stopping = False
        self._lock = threading.Lock()  # pending calls, the end
        self._send_lock = threading.Lock()
        self._pending: dict[int, Future] = {}
        self._ids = itertools.count()
        self._ready: Future = Future()
        self._done = threading.Event()  # the node is done, or gone
        self._sent_demand: list[Hashable] | None = None
        self._demand_lock = threading.Lock()  # the list told last is the newest taken
        self.snapshots = 0
        self.replaced = 0
        self.stream_dropped = 0
        self.replica_dropped = 0
        self.transfer_ms = float("nan")
        self.send_ms = float("nan")
        self._transfer_sum_ms = 0.0

    @classmethod
    def start(cls, live: LiveNode, timeout_s: float) -> NodeLink:
        """Spawn the node's process for ``live`` and wait until it serves (at most
        ``timeout_s`` s, its start included); ServeError naming why it did not. Call it from
        a thread that lives as long as the node (the main thread): the kernel's signal that
        ends the node's process with this one follows the thread that started it."""
        link = cls(live)
        ctx = mp.get_context("spawn")
        news_recv, news_send = ctx.Pipe(duplex=False)
        with contextlib.suppress(AttributeError, OSError):  # Linux: a snapshot in fewer writes
            fcntl.fcntl(news_send.fileno(), fcntl.F_SETPIPE_SZ, NEWS_PIPE_BYTES)
        link._conn, child_conn = ctx.Pipe()
        link._news = news_recv
        queue_ = live.queue if hasattr(live, "queue") else None
        replica = live.sql_replica
        sql_feed = None if replica is None else (str(replica.folder), live.sql_seed_period_s)
        # a spawned child imports the caller's main module again (as __mp_main__): scripts
        # that make a process-backed node need a ``if __name__ == "__main__"`` guard
        link.proc = ctx.Process(
            target=_node_main,
            args=(type(live), live.spawn_args(), queue_, news_send, child_conn, os.getpid(),
                  timeout_s, sql_feed),
            # not a daemon: the node starts the odometry process of its own
            daemon=False, name="wm-node",
        )  # fmt: skip
        link.proc.start()
        # multiprocessing waits at exit for a process that is no daemon, and the node's
        # process waits for this one to end: stop it first (exit handlers run newest first)
        atexit.register(link._at_exit)
        news_send.close()
        child_conn.close()
        link.alive = True
        threading.Thread(target=link._read_replies, name="wm-node-replies", daemon=True).start()
        try:
            info, why = link._ready.result(timeout_s + 30.0)  # the spawn's imports too
        except TimeoutError:
            link._kill()
            raise ServeError(f"the node's process did not start within {timeout_s} s") from None
        if info is None:
            link._kill()
            raise ServeError(f"the live node could not start: {why}")
        link.info = info
        live.demand.on_new = link.send_demand
        threading.Thread(target=link._read_news, name="wm-node-news-in", daemon=True).start()
        link.send_demand()
        return link

    # --- requests ------------------------------------------------------------------------

    def call(self, fn: Callable, args: tuple, timeout_s: float) -> Any:
        """``fn(node_side_live, *args)`` in the node's process (``LiveNode.call``)."""
        fut: Future = Future()
        with self._lock:
            if not self.alive:
                raise ServeError(self._why_gone())
            ident = next(self._ids)
            self._pending[ident] = fut
        try:
            send_message(self._conn, ("call", ident, fn, args), self._send_lock)
            kind, value = fut.result(timeout_s)
        except OSError:
            raise ServeError(self._why_gone()) from None
        except TimeoutError:
            raise ServeError(
                f"the node's process gave no answer to {fn.__name__} within {timeout_s:g} s"
            ) from None
        finally:
            with self._lock:
                self._pending.pop(ident, None)
        if kind == "ok":
            return value
        if kind == "http":
            raise HTTPException(*value)
        raise value

    def tell(self, kind: str, value: Any) -> None:
        """A message the node's process takes without answering; nothing once it is gone."""
        if not self.alive:
            return
        with contextlib.suppress(OSError):
            send_message(self._conn, (kind, value), self._send_lock)

    def send_demand(self) -> None:
        """Tell the node the views asked for lately, when they changed since last told."""
        with self._demand_lock:
            wanted = self.live.demand.wanted()
            if wanted != self._sent_demand:
                self._sent_demand = wanted
                self.tell("demand", wanted)

    def _read_replies(self) -> None:
        while True:
            try:
                msg = recv_message(self._conn)
            except (EOFError, OSError):
                break
            if msg[0] == "reply":
                with self._lock:
                    fut = self._pending.get(msg[1])
                if fut is not None and not fut.done():
                    fut.set_result(msg[2])
            elif msg[0] == "ready":
                self._ready.set_result((msg[1], msg[2]))
            elif msg[0] == "stopped":
                break
        self._gone()

    # --- news ----------------------------------------------------------------------------

    def _read_news(self) -> None:
        while True:
            try:
                news: NodeNews = recv_message(self._news)
            except (EOFError, OSError):
                break
            self._install(news)
            if news.final:
                self._done.set()
        self._gone()

    def _install(self, news: NodeNews) -> None:
        live = self.live
        sink = live.stream_sink
        for message in news.stream:  # before the status: a stream ends after its last cycle
            if sink is not None:
                sink(message)
        replica = live.sql_replica
        if news.replica and replica is not None:
            replica.offer(news.replica)
            if news.snapshot is not None:  # SQL answers as of the snapshot's cycle, as others
                replica.wait_applied(APPLY_WAIT_S)
        with self._lock:  # never over the error of a process found gone
            if not self.alive:
                return
            if news.snapshot is not None:
                live.snapshot = news.snapshot
                self.snapshots += 1
                self.transfer_ms = 1e3 * (time.monotonic() - news.posted_t)
                self._transfer_sum_ms += self.transfer_ms
            if news.status is not None:  # news of stream messages alone keeps the status
                live.status = news.status
        self.replaced, self.stream_dropped = news.replaced, news.stream_dropped
        self.replica_dropped = news.replica_dropped
        self.send_ms = news.send_ms
        if news.snapshot is not None:
            self.send_demand()  # what expired since, or changed its order

    # --- the end -------------------------------------------------------------------------

    def _why_gone(self) -> str:
        if self.stopping:
            return "the live node is not running (stopped)"
        code = self.proc.exitcode
        return f"the node's process ended unexpectedly (exit code {code})"

    def _gone(self) -> None:
        """Either pipe ended: the node's process is gone (or going). Fail every request in
        flight; an end not asked for is an error in the status and drops the snapshot."""
        with self._lock:
            if not self.alive:
                return
            self.alive = False
            pending = list(self._pending.values())
        if not self.stopping:
            self.proc.join(2.0)  # for its exit code
        why = self._why_gone()
        if not self.stopping:
            self.live.status = dataclasses.replace(self.live.status, error=why)
            self.live.snapshot = None
        for fut in pending:
            if not fut.done():
                fut.set_result(("error", ServeError(why)))
        if not self._ready.done():
            self._ready.set_result((None, why))
        self._done.set()

    def wait(self, timeout_s: float | None) -> bool:
        """Wait until the node is done (or its process gone); whether it is done."""
        self._done.wait(timeout_s)
        return self.live.status.done

    def stop(self, timeout_s: float) -> None:
        """Tell the node's process to stop, finish the node and flush the KD; wait for it
        (``timeout_s`` s), then end it by force."""
        self.stopping = True
        atexit.unregister(self._at_exit)
        self.tell("stop", None)
        self.proc.join(timeout_s)
        if self.proc.is_alive():
            self._kill()
        self._done.wait(2.0)  # the final news, read by now unless the process was killed
        self._gone()

    def _at_exit(self) -> None:
        if self.proc.is_alive() and not self.stopping:
            self.live.stop()

    def _kill(self) -> None:
        self.stopping = True
        self.proc.terminate()
        self.proc.join(5.0)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(5.0)

    def figures(self) -> dict:
        """``node_process`` of ``/v1/status`` (module docstring)."""

        def ms(v: float) -> float | None:
            return None if v != v else round(v, 3)  # NaN: none yet

        n = self.snapshots
        return {
            "pid": self.proc.pid, "alive": self.alive, "snapshots": n,
            "replaced": self.replaced, "transfer_ms": ms(self.transfer_ms),
            "mean_transfer_ms": ms(self._transfer_sum_ms / n) if n else None,
            "send_ms": ms(self.send_ms), "stream_dropped": self.stream_dropped,
            "replica_dropped": self.replica_dropped,
        }  # fmt: skip
