"""Opening a KD costs no needless imports (a 10 s log's run pays them in its wall time)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

import kd_store
from kd_store import Level, State


def test_opening_and_reopening_a_kd_does_not_load_pandas(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    with kd_store.open(path) as kd:  # states in two frames, interleaved, to be read back
        kd.begin_cycle(0)
        a = kd.add_entity("a", Level.OBJECT, noteworthy=True).id
        b = kd.add_entity("b", Level.OBJECT, noteworthy=True).id
        for t in (1, 2):
            kd.observe(a, State(t, "world", (t, 0, 0)))
            kd.observe(b, State(t, "odom", (0, t, 0)))
    code = (
        "import sys, kd_store\n"
        f"kd = kd_store.open({str(path)!r})\n"
        f"s = kd.get({a}).state, kd.get({b}).state\n"
        "print(s[0].frame, s[0].position_xyz[0], s[1].frame, s[1].position_xyz[1])\n"
        "print('pandas' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    frame_a, xa, frame_b, yb, pandas = out.stdout.split()
    assert (frame_a, frame_b) == ("world", "odom")
    assert np.isclose(float(xa), 2.0) and np.isclose(float(yb), 2.0)
    assert pandas == "False"


def test_leaving_a_throwaway_kd_skips_the_flush() -> None:
    """Closing discards an in-memory KD, so its clean exit does not write it to DuckDB first
    (the write would load pandas through pyarrow: a quarter second of a short run)."""
    code = (
        "import sys, kd_store\n"
        "from kd_store import Level, State\n"
        "with kd_store.open() as kd:\n"
        "    kd.begin_cycle(0)\n"
        "    e = kd.add_entity('a', Level.OBJECT, noteworthy=True).id\n"
        "    kd.observe(e, State(1, 'world', (1, 0, 0)))\n"
        "print('pandas' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False"]
