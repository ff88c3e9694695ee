"""Published read-only snapshots of a KD (``wm run --snapshot S``, docs/kd.md, "Reading a KD
while a node writes it"): with real processes, a reader opens S as often as it likes while
`wm run` writes the KD (no lock error, the entity count never going back, S equal to the KD
at the end); a SIGKILL leaves S whole (`wm check` passes); and S is refused where it would
overwrite the KD or a file that is no earlier snapshot."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import duckdb
import pytest

import kd_store
from wm.config import NodeConfig
from wm.node import WorldModelNode

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}
WM = [sys.executable, "-m", "wm.cli"]


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("snapshot") / "s.mcap"
    return simulate_to_log("default", path, seconds=8.0, seed=45, progress=False)


def _start_run(log: Path, tmp_path: Path, *extra: str) -> subprocess.Popen:
    cmd = [*WM, "run", str(log), "--kd", str(tmp_path / "k.duckdb"), "--no-progress",
           "--snapshot", str(tmp_path / "s.duckdb"), *extra]  # fmt: skip
    return subprocess.Popen(
        cmd, cwd=REPO, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )


def _entities(path: Path) -> list[tuple[int, str, str]]:
    """(id, name, status) of every entity in the KD file ``path``, opened read-only."""
    with kd_store.open(path, read_only=True) as kd:
        rows = kd.sql("SELECT id, name, status FROM entities ORDER BY id").to_pylist()
    return [(r["id"], r["name"], r["status"]) for r in rows]


def _count(path: Path) -> int:
    """Entity frames in the KD file ``path``, opened read-only with plain DuckDB (light: the
    reader must not slow the run it watches on a 2-core machine)."""
    con = duckdb.connect(str(path), read_only=True)
    try:
        return int(con.sql("SELECT count(*) FROM entity_frames").fetchall()[0][0])
    finally:
        con.close()


def test_a_reader_opens_the_snapshot_while_wm_run_writes(log: Path, tmp_path: Path) -> None:
    snapshot, report = tmp_path / "s.duckdb", tmp_path / "r.json"
    proc = _start_run(log, tmp_path, "--snapshot-every", "1", "--report", str(report))
    counts: list[int] = []
    try:
        deadline = time.monotonic() + 300
        while proc.poll() is None and time.monotonic() < deadline:
            if snapshot.exists():  # every open succeeds: no lock error, no half-written file
                counts.append(_count(snapshot))
            time.sleep(0.1)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-2000:]
    assert len(counts) >= 3, f"too few reads while the run went on: {counts}"
    assert counts == sorted(counts), f"the entity count went back: {counts}"
    assert _entities(snapshot) == _entities(tmp_path / "k.duckdb")
    s = json.loads(report.read_text())["kd_snapshot"]
    assert s["published"] >= 5 and not s["failed"]  # 8 s of log, every 1 s, and the end
    assert 0 < s["median_ms"] <= s["max_ms"]
    assert not (tmp_path / ".s.duckdb.partial").exists()


def test_sigkill_during_the_run_leaves_a_sound_snapshot(log: Path, tmp_path: Path) -> None:
    snapshot = tmp_path / "s.duckdb"
    proc = _start_run(log, tmp_path, "--snapshot-every", "0.5")
    try:
        deadline = time.monotonic() + 120
        while not snapshot.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        first = snapshot.stat().st_mtime_ns
        while snapshot.stat().st_mtime_ns == first and proc.poll() is None:
            time.sleep(0.02)  # a second one published: the run is publishing as it goes
        time.sleep(0.3)  # and kill it anywhere, a copy in progress perhaps
        assert proc.poll() is None, "the run ended before it could be killed"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    check = subprocess.run([*WM, "check", str(snapshot)], cwd=REPO, env=ENV,
                           capture_output=True, text=True, timeout=120)  # fmt: skip
    assert check.returncode == 0, check.stdout + check.stderr
    assert _entities(snapshot), "the snapshot holds no entity"


def _wm_run_refused(log: Path, tmp_path: Path, snapshot: Path, capsys) -> str:
    """``wm run --snapshot snapshot`` (in this process: it is refused before any work) exits
    with status 2 without making the KD; returns what it printed on stderr."""
    from wm.cli import main

    argv = ["run", str(log), "--kd", str(tmp_path / "k.duckdb"), "--no-progress",
            "--snapshot", str(snapshot)]  # fmt: skip
    assert main(argv) == 2
    assert not (tmp_path / "k.duckdb").exists(), "the refused run made a KD file"
    return capsys.readouterr().err


def test_wm_run_refuses_the_kd_itself_and_a_file_that_is_no_snapshot(
    log: Path, tmp_path: Path, capsys
) -> None:
    assert "is the KD file itself" in _wm_run_refused(log, tmp_path, tmp_path / "k.duckdb", capsys)
    text = tmp_path / "notes.txt"
    text.write_text("mine")
    assert "no snapshot published there" in _wm_run_refused(log, tmp_path, text, capsys)
    assert text.read_text() == "mine"
    other = tmp_path / "other.duckdb"  # another KD (no snapshot of anything there)
    kd_store.open(other).close()
    before = other.read_bytes()
    assert "no snapshot published there" in _wm_run_refused(log, tmp_path, other, capsys)
    assert other.read_bytes() == before


def test_publish_snapshot_replaces_only_an_earlier_snapshot(tmp_path: Path) -> None:
    snapshot = tmp_path / "s.duckdb"
    with kd_store.open(tmp_path / "a.duckdb") as kd:
        kd.add_entity("a", kd_store.Level.OBJECT, noteworthy=True)
        assert kd.publish_snapshot(snapshot) == snapshot.resolve()
        with pytest.raises(kd_store.KDError, match="is the KD file itself"):
            kd.publish_snapshot(tmp_path / "a.duckdb")
        with pytest.raises(kd_store.KDError, match="does not exist"):
            kd.publish_snapshot(tmp_path / "no" / "s.duckdb")
    reader = duckdb.connect(str(snapshot), read_only=True)  # holds the old snapshot open
    try:
        with kd_store.open(tmp_path / "b.duckdb") as kd:  # a later run, the same snapshot path
            kd.add_entity("b1", kd_store.Level.OBJECT, noteworthy=True)
            kd.add_entity("b2", kd_store.Level.OBJECT, noteworthy=True)
            kd.publish_snapshot(snapshot)
            with pytest.raises(kd_store.KDError, match="no snapshot published there"):
                kd.publish_snapshot(tmp_path / "a.duckdb")  # a KD, no snapshot
        assert reader.sql("SELECT count(*) FROM entity_frames").fetchall()[0][0] == 1
    finally:
        reader.close()
    assert [e[1] for e in _entities(snapshot)] == ["b1", "b2"]
    with pytest.raises(kd_store.KDError, match="throwaway"):
        kd_store.open(":memory:").publish_snapshot(snapshot)


def test_a_node_refuses_a_snapshot_of_a_throwaway_kd(tmp_path: Path) -> None:
    with pytest.raises(kd_store.KDError, match="throwaway"):
        WorldModelNode(kd_store.open(":memory:"), NodeConfig(snapshot_path=str(tmp_path / "s")))
    with pytest.raises(ValueError, match="snapshot_every_s"):
        NodeConfig(snapshot_every_s=-1.0)
