"""Reliability: a writer killed with SIGKILL mid-stream leaves every flushed batch whole and
the file readable; readers in other threads see consistent snapshots while a writer flushes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

import kd_store
from kd_store import Level, StateBatch, Status

N_ENTITIES = 200
STEPS = 10  # rows per batch = N_ENTITIES * STEPS; batch b holds t_ns in [b*100, b*100 + 10)
ROWS = N_ENTITIES * STEPS

WRITER = f"""
import sys
import numpy as np
import kd_store
kd = kd_store.open(sys.argv[1])
if len(kd.entity_ids()) == 0:
    for i in range({N_ENTITIES}):
        kd.add_entity(f"e{{i}}", 4, id=i, status="confirmed", confidence=1.0)
    kd.flush()
done = kd.sql("SELECT coalesce(max(t_ns) // 100 + 1, 0) AS b FROM entity_states")["b"][0]
b = int(done.as_py())
print("start", b, flush=True)
ids = np.tile(np.arange({N_ENTITIES}), {STEPS})
while True:
    t = b * 100 + np.repeat(np.arange({STEPS}), {N_ENTITIES})
    pos = np.random.default_rng(b).normal(size=(len(ids), 3))
    kd.ingest(kd_store.StateBatch(ids, t, "world", pos))
    kd.flush()
    print("flushed", b, flush=True)
    b += 1
"""


def _batches_on_disk(path: Path) -> dict[int, int]:
    with kd_store.open(path) as kd:
        t = kd.sql("SELECT t_ns // 100 AS b, count(*) AS n FROM entity_states GROUP BY b")
        assert len(kd.entity_ids()) == N_ENTITIES
        for f in kd.entities():  # every stored frame loads and is valid
            assert f.status == Status.CONFIRMED
        return dict(zip(t["b"].to_pylist(), t["n"].to_pylist(), strict=True))


def _run_and_kill(path: Path, after_batches: int, delay_s: float) -> tuple[int, int]:
    """Start a writer, SIGKILL it ``delay_s`` after its ``after_batches``-th flush report.
    Returns (first batch it wrote, last batch it reported flushed)."""
    env = {**os.environ, "PYTHONPATH": str(Path(kd_store.__file__).parents[1])}
    p = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True, env=env
    )
    guard = threading.Timer(60.0, p.kill)  # a hung writer fails the test instead of hanging it
    guard.start()
    try:
        first = int(p.stdout.readline().split()[1])
        last = -1
        for _ in range(after_batches):
            line = p.stdout.readline()
            assert line.startswith("flushed"), line
            last = int(line.split()[1])
        time.sleep(delay_s)
        p.send_signal(signal.SIGKILL)
    finally:
        guard.cancel()
        p.kill()
        p.wait()
    assert p.returncode == -signal.SIGKILL
    return first, last


def test_sigkill_mid_stream_keeps_every_flushed_batch_whole(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    for delay_s in (0.0, 0.013):
        first, last = _run_and_kill(path, after_batches=4, delay_s=delay_s)
        counts = _batches_on_disk(path)
        # every reported batch is there; at most the one in flight beyond; none torn
        assert set(range(last + 1)) <= set(counts) <= set(range(last + 2)), counts
        assert all(n == ROWS for n in counts.values()), counts
        assert first == 0 or first in counts


def test_readers_see_consistent_snapshots_while_writer_flushes(tmp_path: Path) -> None:
    kd = kd_store.open(tmp_path / "kd.duckdb")
    for i in range(N_ENTITIES):
        kd.add_entity(f"e{i}", Level.OBJECT, id=i, status="confirmed", confidence=1.0)
    kd.flush()
    ids = np.tile(np.arange(N_ENTITIES), STEPS)
    n_batches = 25
    problems: list[str] = []
    seen: list[int] = []
    stop = threading.Event()

    def read() -> None:
        r = kd.reader()
        last = 0
        while not stop.is_set():
            with r.snapshot():
                per = r.sql("SELECT t_ns // 100 AS b, count(*) AS n FROM entity_states GROUP BY b")
                total = r.sql("SELECT count(*) AS n FROM entity_states")["n"][0].as_py()
            counts = per["n"].to_pylist()
            if any(c != ROWS for c in counts) or total != ROWS * len(counts):
                problems.append(f"torn snapshot: {counts} total {total}")
            if len(counts) < last:
                problems.append(f"went back from {last} to {len(counts)} batches")
            last = len(counts)
            seen.append(last)
        r.close()

    readers = [threading.Thread(target=read) for _ in range(2)]
    for t in readers:
        t.start()
    for b in range(n_batches):
        t_ns = b * 100 + np.repeat(np.arange(STEPS), N_ENTITIES)
        kd.ingest(StateBatch(ids, t_ns, "world", np.zeros((len(ids), 3))))
        kd.flush()
    stop.set()
    for t in readers:
        t.join()
    assert problems == []
    assert len(seen) > 2 and max(seen) <= n_batches
    assert kd.sql("SELECT count(*) AS n FROM entity_states")["n"][0].as_py() == n_batches * ROWS
    kd.close()
