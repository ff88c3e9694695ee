"""SQL of a live node in a process of its own, answered in the server's process from read-only
copies of the KD (wm.serve_sql), over real HTTP on localhost (uvicorn): a 503 saying so before
the first copy; an answer equal to a direct read of the KD at the copy's cycle, with its
staleness; the same refusals as SQL over the KD itself, by DuckDB's configuration; and the copy
with its write-ahead log alone (no checkpoint) equal to the KD it was taken of. The log and the
request helper are test_wm_serve's."""

from __future__ import annotations

import json
import time
import urllib.request
from pathlib import Path

import pytest
from serving import served

import kd_store

pytest.importorskip("fastapi")
pytest.importorskip("uvicorn")

from test_wm_serve import TOKEN, call, log  # noqa: F401  (log: a fixture)

QUERY = "SELECT id, status FROM entities ORDER BY id"
REFUSED = [
    # SELECTs reading another file: the statement check passes them, DuckDB refuses them
    ("SELECT * FROM read_csv('/etc/passwd')", "reads the KD's own views only"),
    ("SELECT * FROM read_text('/etc/hostname')", "reads the KD's own views only"),
    ("COPY entities TO '{tmp}/leak.csv'", "only one read-only SELECT"),
    ("ATTACH '{tmp}/other.duckdb' AS other", "only one read-only SELECT"),
    ("INSTALL httpfs", "only one read-only SELECT"),
    ("LOAD httpfs", "only one read-only SELECT"),
    ("SET enable_external_access = true", "only one read-only SELECT"),
    ("PRAGMA enable_profiling", "only one read-only SELECT"),
    ("SELECT 1; DROP TABLE entities", "only one read-only SELECT"),
]


def _raw_sql(base: str, query: str) -> tuple[int, dict, dict]:
    """(status, JSON, headers) of one ``POST /v1/sql``, no retry."""
    req = urllib.request.Request(
        base + "/v1/sql",
        data=json.dumps({"query": query}).encode(),
        headers={"Content-Type": "application/json", "Authorization": f"Bearer {TOKEN}"},
    )
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read()), {k.lower(): v for k, v in r.headers.items()}
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"null"), {k.lower(): v for k, v in e.headers.items()}


def _sql_at(base: str, query: str, cycle_t_ns: int, timeout_s: float = 60.0) -> dict:
    """The first answer to ``query`` read from a copy of cycle ``cycle_t_ns`` or later."""
    deadline = time.time() + timeout_s
    while True:
        code, ans, _ = _raw_sql(base, query)
        if code == 200 and ans["cycle_t_ns"] >= cycle_t_ns:
            return ans
        assert code in (200, 503), ans
        assert time.time() < deadline, f"no copy of cycle {cycle_t_ns} in {timeout_s} s: {ans}"
        time.sleep(0.1)


@pytest.fixture(scope="module")
def finished(log, tmp_path_factory):  # noqa: F811
    """A node in a process of its own that replayed the log to its end as fast as it could,
    copying its KD for SQL every 0.2 s, served on localhost; yields (live, base URL, KD
    path, the answer of the very first SQL request with its headers)."""
    from wm.serve import LiveNode, create_app

    kd_path = tmp_path_factory.mktemp("serve-sql") / "live.duckdb"
    live = LiveNode(log, kd_path, rate=0.0, process=True)
    live.sql_copy_period_s = 0.2
    live.start()
    try:
        with served(create_app(live, token=TOKEN)) as base:
            first = _raw_sql(base, QUERY)  # nobody asked for SQL before: no copy yet
            assert live.wait(600) and not live.status.error, live.status.error
            yield live, base, kd_path, first
    finally:
        live.stop()


def test_sql_before_the_first_copy_is_a_503_that_says_so(finished) -> None:
    """The first SQL request of a node in a process of its own finds no copy of the KD (SQL
    was never asked for): a 503 naming why, with Retry-After, never a 500."""
    _, _, _, (code, ans, headers) = finished
    assert code == 503, ans
    assert "no read-only copy of the KD for SQL yet" in ans["detail"]
    assert int(headers["retry-after"]) >= 1


@pytest.mark.parametrize(("query", "names"), REFUSED)
def test_sql_over_a_copy_is_refused_outside_the_kd(finished, tmp_path, query, names) -> None:
    """Reading a file, COPY TO, ATTACH, INSTALL, LOAD, SET, PRAGMA and a second statement are
    refused with a 400 naming the statement, and leave nothing behind; a reader of another
    file (read_csv, read_text: SELECTs, which the statement check lets through) is refused by
    the copy's DuckDB configuration itself."""
    live, base, _, _ = finished
    assert live.running
    _sql_at(base, "SELECT 1", 0)  # a copy is open
    q = query.format(tmp=tmp_path)
    code, ans, _ = _raw_sql(base, q)
    assert code == 400, ans
    assert names in ans["detail"] and q in ans["detail"]
    assert not list(tmp_path.iterdir())  # no file written, none attached


def test_the_copys_connection_has_external_access_off(finished) -> None:
    """Not parsing alone: the server's connection to the copy has DuckDB's external access off
    and its configuration locked."""
    live, base, _, _ = finished
    assert live.running
    q = (
        "SELECT current_setting('enable_external_access') AS ext, "
        "current_setting('lock_configuration') AS locked"
    )
    ans = _sql_at(base, q, 0)
    assert ans["rows"] == [[False, True]]


def test_sql_answers_an_arrow_stream_when_asked(finished) -> None:
    """``Accept: application/vnd.apache.arrow.stream``: the same rows as the JSON answer of
    the same cycle, as an Arrow IPC stream whose metadata and headers carry the cycle."""
    import pyarrow as pa

    _, base, _, _ = finished
    newest = call(base, "/v1/status")[1]["cycle_t_ns"]
    as_json = _sql_at(base, QUERY, newest)
    req = urllib.request.Request(
        base + "/v1/sql",
        data=json.dumps({"query": QUERY}).encode(),
        headers={
            "Content-Type": "application/json",
            "Authorization": f"Bearer {TOKEN}",
            "Accept": "application/vnd.apache.arrow.stream",
        },
    )
    with urllib.request.urlopen(req, timeout=30) as r:
        assert r.headers["content-type"] == "application/vnd.apache.arrow.stream"
        cycle = int(r.headers["x-cycle-t-ns"])
        table = pa.ipc.open_stream(r.read()).read_all()
    assert cycle == as_json["cycle_t_ns"] == json.loads(table.schema.metadata[b"cycle_t_ns"])
    assert table.column_names == ["id", "status"]
    assert [list(row.values()) for row in table.to_pylist()] == as_json["rows"]
    from wm.client import Client

    by_client = Client(base, TOKEN).sql_table(QUERY)
    assert by_client.equals(table) and by_client.schema.metadata == table.schema.metadata


def test_sql_reads_a_copy_equal_to_the_kd_at_its_cycle(finished) -> None:
    """(Last of the tests over ``finished``: it stops the node.) At the end of the log the
    answer comes from a copy of the last cycle (staleness 0,
    ``/v1/status`` says the source is a copy, opened in this process) and equals the same
    query over the KD file itself, read directly once the node has closed it."""
    live, base, kd_path, _ = finished
    code, st = call(base, "/v1/status")
    newest = st["cycle_t_ns"]
    assert code == 200 and st["done"] and newest > 0
    ans = _sql_at(base, QUERY, newest)
    assert ans["cycle_t_ns"] == newest == ans["newest_cycle_t_ns"] and ans["staleness_ns"] == 0
    assert len(ans["rows"]) >= 5 and ans["columns"] == ["id", "status"]
    code, st = call(base, "/v1/status")
    sql = st["sql"]
    assert sql["source"] == "copy" and sql["copies_opened"] >= 1 and sql["open_failures"] == 0
    assert sql["cycle_t_ns"] == newest and sql["staleness_ns"] == 0
    assert sql["copy_ms"] > 0 and sql["file_bytes"] > 0
    # the copies lie in a folder of the server's: never the KD's own folder
    assert not any(p.name.startswith("kd-") for p in kd_path.parent.iterdir())
    counted = _sql_at(base, "SELECT count(*) AS n FROM entities", newest)["rows"][0][0]
    live.stop()  # the node's process flushes and closes the KD: now it can be read directly
    with kd_store.open(kd_path, read_only=True) as kd:
        direct = kd.sql(QUERY).to_pylist()
        n = kd.sql("SELECT count(*) AS n FROM entities")["n"][0].as_py()
    assert [[r["id"], r["status"]] for r in direct] == ans["rows"]
    assert counted == n == len(direct)


def test_a_copy_with_its_log_equals_the_kd_it_was_taken_of(tmp_path: Path) -> None:
    """A KD written and flushed (its changes in the write-ahead log, no checkpoint) copied with
    ``copy_committed``: the copy opened read-only (the log replayed) holds what the KD does;
    a later write to the KD is not in it; the server's SQLCopies answers from it, 503-style
    NoCopyYet before it has one, and removes its folder at the end."""
    from kd_store.query import QueryLimits
    from wm.serve_sql import NoCopyYet, SQLCopies, SQLCopy

    folder = tmp_path / "copies"
    folder.mkdir()
    copies = SQLCopies(folder)
    with pytest.raises(NoCopyYet):
        copies.query("SELECT 1", QueryLimits())
    with kd_store.open(tmp_path / "a.duckdb") as kd:
        kd.add_entity("a", kd_store.Level.OBJECT, noteworthy=True)
        kd.add_entity("b", kd_store.Level.OBJECT, noteworthy=True)
        kd.flush()
        assert Path(f"{tmp_path / 'a.duckdb'}.wal").stat().st_size > 0  # not checkpointed
        path = folder / "kd-1.duckdb"
        file_bytes, wal_bytes = kd.copy_committed(path)
        assert wal_bytes > 0
        expected = kd.sql("SELECT id, name FROM entities ORDER BY id").to_pylist()
        kd.add_entity("c", kd_store.Level.OBJECT, noteworthy=True)
        kd.flush()  # after the copy: not in it
        copies.offer(SQLCopy(str(path), 7, 1, 1.0, file_bytes, wal_bytes))
        deadline = time.time() + 30
        while copies.copies_opened < 1 and time.time() < deadline:
            time.sleep(0.02)
        table, copy = copies.query("SELECT id, name FROM entities ORDER BY id", QueryLimits())
    assert copy.cycle_t_ns == 7 and table.to_pylist() == expected
    assert [r["name"] for r in expected] == ["a", "b"]
    with pytest.raises(kd_store.KDError, match="only a KD file open for writing"):
        kd_store.open(":memory:").copy_committed(folder / "m.duckdb")
    copies.close()
    assert not folder.exists()
