"""Untrusted SQL over a KD file (kd_store.query, `wm query`): it reads the KD's views and
nothing else. DuckDB itself refuses files, folders, URLs and extensions (external access
off), and the limits cannot be lifted from the query (configuration locked)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import duckdb
import pytest

import kd_store
from kd_store import KDError, Level, ResultTooLarge, State, Status
from kd_store.query import MB, QueryLimits, query_file

REPO = Path(__file__).resolve().parents[1]


def _three_trees(kd: kd_store.KnowledgeDatabase) -> None:
    """Three confirmed trees at x = 1, 2 and 5 m on the world x axis."""
    for i, x in enumerate((1.0, 2.0, 5.0)):
        kd.add_entity(
            f"tree{i}", Level.OBJECT, status=Status.CONFIRMED, confidence=0.9,
            generic_classes=("tree",),
            state=State(t_ns=1_000, frame="world", position_xyz=(x, 0.0, 0.0)),
        )  # fmt: skip


@pytest.fixture(scope="module")
def kd_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("kd") / "run.kd"
    with kd_store.open(path) as kd:
        _three_trees(kd)
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


def test_a_result_over_the_row_limit_is_refused_before_it_is_read_whole(kd_file):
    """Ten million rows against the default limit of a million: refused with the limit and
    the query in the words, and the KD still answers a query under the limit."""
    sql = "SELECT * FROM range(10_000_000)"
    with pytest.raises(ResultTooLarge, match=r"1,000,000 rows \(max_rows\)") as e:
        query_file(kd_file, sql)
    assert sql in str(e.value) and isinstance(e.value, KDError)
    assert query_file(kd_file, "SELECT * FROM range(1_000_000)").num_rows == 1_000_000
    three = "SELECT id FROM entities"
    assert query_file(kd_file, three, QueryLimits(max_rows=3)).num_rows == 3
    with pytest.raises(ResultTooLarge, match="2 rows"):
        query_file(kd_file, three, QueryLimits(max_rows=2))


def test_a_result_over_the_byte_limit_is_refused(kd_file):
    sql = "SELECT range, repeat('x', 100) AS s FROM range(100_000)"  # about 11 MB of Arrow
    with pytest.raises(ResultTooLarge, match=r"limit of 1\.0 MB \(max_bytes\)") as e:
        query_file(kd_file, sql, QueryLimits(max_bytes=MB))
    assert sql in str(e.value)
    assert query_file(kd_file, sql, QueryLimits(max_bytes=64 * MB)).num_rows == 100_000


def test_one_huge_value_is_refused_with_a_clear_error(kd_file):
    """A 2 GB string: DuckDB's memory limit does not bound one value, so DuckDB builds it
    (about 20 s and a few GB here); the byte limit then refuses it, or on a slow host the
    time limit stops it: either way a KDError naming the query, not a crash."""
    sql = "SELECT repeat('x', 2000000000) AS s"
    with pytest.raises(KDError, match="limit") as e:
        query_file(kd_file, sql)
    assert sql in str(e.value)


def test_served_settings_use_two_threads_like_the_others(tmp_path):
    """A served KD (the live node's writer and its SQL readers) runs with the same two
    DuckDB threads as a sandboxed query, whatever the host's core count."""
    from kd_store.query import sandbox_settings, served_settings

    assert served_settings()["threads"] == sandbox_settings(QueryLimits())["threads"] == 2
    assert "memory_limit" not in served_settings()
    with kd_store.open(tmp_path / "served.duckdb", settings=served_settings()) as kd:
        got = kd.sql("SELECT current_setting('threads') AS n").to_pylist()
    assert got == [{"n": 2}]


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


def test_wm_query_refuses_a_result_over_its_row_limit_in_bounded_memory(kd_file, tmp_path):
    """``wm query`` of ten million rows: exit 2 with the limit and the query named, its peak
    memory far below what holding and printing the whole result would take; ``--max-rows``
    raises the limit, and the print count is ``--show-rows``."""
    sql = "SELECT * FROM range(10_000_000)"
    # the process's own high-water mark (VmHWM: ru_maxrss would carry pytest's over the exec)
    peak = (
        "import re, runpy, sys\n"
        "try:\n    runpy.run_module('wm.cli', run_name='__main__')\n"
        "finally:\n    hwm = re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read())\n"
        "    print('peak_kb', hwm.group(1), file=sys.stderr)"
    )
    r = subprocess.run(
        [sys.executable, "-c", peak, "query", str(kd_file), sql], cwd=tmp_path,
        capture_output=True, text=True, timeout=120,
        env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"},
    )  # fmt: skip
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "1,000,000 rows (max_rows)" in r.stderr and sql in r.stderr
    peak_mb = int(r.stderr.split("peak_kb")[1]) / 1024
    assert peak_mb < 600, f"wm query peaked at {peak_mb:.0f} MB"
    out = tmp_path / "ten.parquet"
    r = wm("query", str(kd_file), "SELECT * FROM range(10)", "--max-rows", "9",
           "--parquet", str(out), cwd=tmp_path)  # fmt: skip
    assert r.returncode == 2 and "9 rows (max_rows)" in r.stderr and not out.exists()
    r = wm("query", str(kd_file), "SELECT * FROM range(10)", "--max-rows", "10",
           "--show-rows", "3", cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "... 7 more rows" in r.stdout and "(10 rows)" in r.stdout


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


def test_wm_query_parquet_replaces_an_existing_file_only_with_overwrite(kd_file, tmp_path):
    import pyarrow.parquet as pq

    out = tmp_path / "earlier.parquet"
    out.write_bytes(b"an earlier result")
    r = wm("query", str(kd_file), "SELECT id FROM entities", "--parquet", str(out), cwd=tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "exists" in r.stderr and "--overwrite" in r.stderr and str(out) in r.stderr
    assert out.read_bytes() == b"an earlier result"
    r = wm("query", str(kd_file), "SELECT id FROM entities", "--parquet", str(out),
           "--overwrite", cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert pq.read_table(out).num_rows == 3
    fresh = tmp_path / "new.parquet"
    r = wm("query", str(kd_file), "SELECT id FROM entities", "--parquet", str(fresh), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert pq.read_table(fresh).num_rows == 3


# --- kd.sql, the KD's own SQL in a Python program -------------------------------------------


@pytest.fixture(params=["memory", "file"])
def open_kd(request, tmp_path):
    """A KD with three trees, in memory or in a file, open for writing."""
    kd = kd_store.open(":memory:" if request.param == "memory" else tmp_path / "own.kd")
    _three_trees(kd)
    yield kd
    kd.close()


@pytest.mark.parametrize(
    "sql",
    [
        "SELECT * FROM read_text('/etc/hostname')",
        "SELECT * FROM read_csv('/etc/passwd')",
        "SELECT * FROM glob('/etc/*')",
        "SELECT * FROM read_blob('/etc/hostname')",
        "SELECT * FROM read_json('/etc/passwd')",
        "SELECT * FROM read_parquet('https://example.com/x.parquet')",
    ],
)
def test_kd_sql_reads_nothing_outside_the_kd(open_kd, sql):
    with pytest.raises(KDError, match=r"refused.*own views only") as e:
        open_kd.sql(sql)
    assert sql in str(e.value)
    with pytest.raises(KDError, match="refused"):
        open_kd.reader().sql(sql)  # another thread's reader: the same connection's walls


@pytest.mark.parametrize(
    "template",
    [
        "COPY (SELECT * FROM entities) TO '{out}'",
        "ATTACH '{out}' AS other",
        "INSTALL sqlite",
        "LOAD sqlite",
        "SET enable_external_access = true",
    ],
)
def test_kd_sql_writes_nothing_and_loads_nothing(open_kd, template, tmp_path):
    out = tmp_path / "leak.csv"
    with pytest.raises(KDError, match="SQL"):
        open_kd.sql(template.format(out=out))
    assert not out.exists()
    # and not by the back door of the connection either: DuckDB refuses it
    with pytest.raises(duckdb.Error, match=r"disabled|locked"):
        open_kd._con.execute(f"COPY (SELECT 1) TO '{out}'")
    assert not out.exists()


def test_kd_sql_still_answers_over_the_views_and_the_kd_still_writes(open_kd, tmp_path):
    t = open_kd.sql(
        "SELECT class_name, count(*) AS n, sum(x) AS sx FROM entities GROUP BY 1"
    ).to_pylist()
    assert t == [{"class_name": "tree", "n": 3, "sx": 8.0}]
    a = open_kd.sql("SELECT * FROM entity_states_as_of(2000) ORDER BY entity_id")
    assert a.num_rows == 3
    # the engine's own file work (flush, Parquet export and import) is not held back
    open_kd.observe(0, State(t_ns=2_000, frame="world", position_xyz=(1.5, 0.0, 0.0)))
    assert open_kd.flush() >= 1
    files = open_kd.export_parquet(tmp_path / "pq")
    assert files and all(f.is_file() for f in files)
    with kd_store.open(":memory:") as copy:
        copy.import_parquet(tmp_path / "pq")
        assert copy.sql("SELECT count(*) AS n FROM entity_states").to_pylist() == [{"n": 4}]
