"""A FastAPI app on real uvicorn, on a free localhost port in a thread, for the API tests; a
live node in either mode (a process of its own, or a thread), and the node's lock held or a
reference worked out where the node is (:meth:`wm.serve.LiveNode.call`: the functions it
runs are module-level, so that the node's process can import them by name)."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator


def free_port() -> int:
    """A localhost TCP port nobody listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def served(app) -> Iterator[str]:
    """``app`` served by uvicorn in a thread until the block ends; yields its base URL. The
    socket is bound here and handed to uvicorn: a port found free and bound later may be
    taken in between (another test's outgoing connection draws from the same ports)."""
    import uvicorn

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = int(sock.getsockname()[1])
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=srv.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.time() + 30
    while not srv.started and time.time() < deadline:
        time.sleep(0.05)
    assert srv.started, "uvicorn did not start"
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        srv.should_exit = True
        thread.join(10)
        sock.close()


# --- a live node in either mode ----------------------------------------------------------------

#: how a test's live node runs: in a process of its own (``wm serve``'s default) or in a thread
#: of the test's process (``--in-process``)
MODES = ("process", "thread")


def start_live(
    log,
    kd_path,
    config=None,
    rate: float = 1.0,
    mode: str = "process",
    seed_period_s: float | None = None,
):
    """A started :class:`wm.serve.LiveNode` replaying ``log`` in ``mode`` (:data:`MODES`);
    ``seed_period_s``: the least time between two seeds of its SQL replica (None: default)."""
    from wm.serve import LiveNode

    live = LiveNode(log, kd_path, config, rate, process=mode == "process")
    if seed_period_s is not None:
        live.sql_seed_period_s = seed_period_s
    return live.start()


def acquire_node_lock(live) -> None:
    """Take the node's lock (a :meth:`wm.serve.LiveNode.call`: in the node's process when it
    runs in one); :func:`release_node_lock` gives it back, from any thread."""
    assert live.lock.acquire(timeout=60), "the node's lock was not free within 60 s"


def release_node_lock(live) -> None:
    live.lock.release()


def node_lock_held(live) -> bool:
    return live.lock.locked()


def node_snapshot_cycle(live) -> int:
    """The newest cycle's time of the node's own copy (-1 before any)."""
    return live.snapshot.cycle_t_ns if live.snapshot is not None else -1


@contextlib.contextmanager
def holding_node_lock(live) -> Iterator[int]:
    """The node's lock held until the block ends (the node waits at its next cycle), as a
    cycle in progress holds it; yields the held cycle's time, once the server holds that
    cycle's copy (in process mode it may still be on its way when the lock is taken)."""
    live.call(acquire_node_lock)
    try:
        held = live.call(node_snapshot_cycle)
        deadline = time.time() + 30
        while live.snapshot is None or live.snapshot.cycle_t_ns != held:
            assert time.time() < deadline, "the held cycle's copy never reached the server"
            time.sleep(0.01)
        yield held
    finally:
        live.call(release_node_lock)


def level_cells(live, level: str, layers, xy, lock: bool = True) -> dict:
    """The node's own map level ``level`` (a :meth:`wm.serve.LiveNode.call`): each of
    ``layers`` at world ``xy`` (N, 2) m as ``MapLevel.read`` gives it (its dtype), under the
    node's lock (``lock`` False: the caller holds it)."""
    with live.lock if lock else contextlib.nullcontext():
        lvl = live.node.stack.level(level)
        return {layer: lvl.read(layer, xy) for layer in layers}
