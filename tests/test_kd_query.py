"""Untrusted SQL over a KD file (kd_store.query, `wm query`): it reads the KD's views and
nothing else. DuckDB itself refuses files, folders, URLs and extensions (external access
off), and the limits cannot be lifted from the query (configuration locked)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

import kd_store
from kd_store import KDError, Level, State, Status
from kd_store.query import QueryLimits, query_file

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def kd_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("kd") / "run.kd"
    with kd_store.open(path) as kd:
        for i, x in enumerate((1.0, 2.0, 5.0)):
            kd.add_entity(
                f"tree{i}", Level.OBJECT, status=Status.CONFIRMED, confidence=0.9,
                generic_classes=("tree",),
                state=State(t_ns=1_000, frame="world", position_xyz=(x, 0.0, 0.0)),
            )  # fmt: skip
    return path


def test_a_select_over_the_views_works(kd_file):
    t = query_file(kd_file, "SELECT count(*) AS n, sum(x) AS sx FROM entities")
    assert t.to_pylist() == [{"n": 3, "sx": 8.0}]


@pytest.mark.parametrize(
    "sql",
    [
        "SELECT * FROM read_csv('/etc/passwd')",
        "SELECT * FROM read_text('/etc/hostname')",
        "SELECT * FROM read_blob('/etc/hostname')",
        "SELECT * FROM glob('/etc/*')",
        "SELECT * FROM read_parquet('/tmp/*.parquet')",
        "SELECT * FROM read_csv('https://example.com/x.csv')",
        "SELECT * FROM sqlite_scan('/tmp/x.db', 't')",
    ],
)
def test_nothing_outside_the_kd_is_reached(kd_file, sql):
    with pytest.raises(KDError, match="SQL"):
        query_file(kd_file, sql)


@pytest.mark.parametrize(
    "sql",
    [
        "SET enable_external_access = true",
        "SET memory_limit = '100GB'",
        "PRAGMA enable_external_access",
        "ATTACH '/tmp/other.db'",
        "COPY (SELECT 1) TO '/tmp/out.csv'",
        "INSTALL sqlite",
        "LOAD sqlite",
        "DELETE FROM entities",
        "SELECT 1; SELECT 2",
    ],
)
def test_only_one_select_is_run(kd_file, sql):
    with pytest.raises(KDError):
        query_file(kd_file, sql)
    assert query_file(kd_file, "SELECT count(*) AS n FROM entities").to_pylist() == [{"n": 3}]


def test_a_query_over_its_time_stops_with_a_clear_error(kd_file):
    slow = "SELECT count(*) FROM range(10000000000) a WHERE a.range % 7 = 3"
    with pytest.raises(KDError, match="limit"):
        query_file(kd_file, slow, QueryLimits(timeout_s=0.5))


def test_a_served_kd_stops_a_reader_query_over_its_time(tmp_path):
    """The live node's SQL path: a KD opened with the served settings, queried through a
    reader of another thread, is interrupted at the limit and still answers afterwards."""
    import kd_store
    from kd_store.query import query_reader, served_settings

    with kd_store.open(tmp_path / "served.duckdb", settings=served_settings()) as kd:
        kd.flush()
        reader = kd.reader()
        slow = "SELECT count(*) FROM range(10000000000) a WHERE a.range % 7 = 3"
        with pytest.raises(KDError, match="limit"):
            query_reader(reader, slow, QueryLimits(timeout_s=0.5))
        assert query_reader(reader, "SELECT count(*) AS n FROM entities").to_pylist() == [{"n": 0}]
        reader.close()


def wm(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "wm.cli", *args], cwd=cwd, capture_output=True, text=True,
        env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}, timeout=120,
    )  # fmt: skip


def test_wm_query_parquet_never_overwrites_the_kd_or_a_folder(kd_file, tmp_path):
    size = kd_file.stat().st_size
    for target, words in (
        (str(kd_file), "is the KD being queried"),
        (str(tmp_path / "out.csv"), "ending in .parquet"),
        (str(tmp_path), "is a folder"),
        (str(tmp_path / "nowhere" / "x.parquet"), "does not exist"),
    ):
        r = wm("query", str(kd_file), "SELECT 1 AS x", "--parquet", target, cwd=tmp_path)
        assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr
    assert kd_file.stat().st_size == size
    assert query_file(kd_file, "SELECT count(*) AS n FROM entities").to_pylist() == [{"n": 3}]
    r = wm("query", str(kd_file), "SELECT * FROM read_csv('/etc/passwd')", cwd=tmp_path)
    assert r.returncode == 2 and "file system operations are disabled" in r.stderr
