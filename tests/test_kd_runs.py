"""Several runs in one KD file: each run's rows carry its run_id in every view, a new run
loads nothing of the earlier ones (its own frame, its own map tiles), any run can be opened
again, an older file is migrated with its rows as run 0, and the integrity check finds rows
of unknown runs or mixed across runs."""

from __future__ import annotations

from pathlib import Path

import duckdb
import numpy as np
import pytest

import kd_store
from kd_store import KDError
from kd_store.check import check_file
from kd_store.persist import RUN_TABLES, SCHEMA_VERSION
from tests.test_kd_persist import build_full_kd

VIEWS = (
    "entities",
    "entity_states",
    "entity_expectations",
    "entity_attributes",
    "events",
    "relations",
    "map_tiles",
)


def _counts(kd: kd_store.KnowledgeDatabase, run: int) -> dict[str, int]:
    return {
        v: kd.sql(f"SELECT count(*) AS n FROM {v} WHERE run_id = {run}")["n"][0].as_py()
        for v in VIEWS
    }


def _two_runs(path: Path) -> tuple[dict[str, int], dict[str, int]]:
    with kd_store.open(path, source="first.mcap") as kd:
        ids0 = build_full_kd(kd)
        kd.put_tile("subsystem", 0, 0, {"elevation": np.ones((4, 4), np.float32)})
        assert kd.run_id == 0
    with kd_store.open(path, run="new", source="second.mcap") as kd:
        assert kd.run_id == 1
        assert list(kd.entities()) == [] and list(kd.events()) == []  # nothing of run 0
        assert kd.get_tile("subsystem", 0, 0) is None and kd.tile_keys() == []
        ids1 = build_full_kd(kd)
        kd.put_tile("subsystem", 0, 0, {"elevation": np.full((4, 4), 2, np.float32)})
    return ids0, ids1


def test_a_new_run_is_a_run_of_its_own_in_every_view(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    ids0, ids1 = _two_runs(path)
    assert not set(ids0.values()) & set(ids1.values())  # ids unique across runs
    with kd_store.open(path, read_only=True) as kd:  # the newest run by default
        assert kd.run_id == 1
        runs = kd.sql("SELECT run_id, source, entities, events FROM runs ORDER BY run_id")
        assert runs["run_id"].to_pylist() == [0, 1]
        assert runs["source"].to_pylist() == ["first.mcap", "second.mcap"]
        assert runs["entities"].to_pylist()[0] == runs["entities"].to_pylist()[1] > 0
        c0, c1 = _counts(kd, 0), _counts(kd, 1)
        assert c0 == c1 and all(n > 0 for n in c0.values()), c0  # the same rows, twice
        assert {f.id for f in kd.entities()} == {
            i for i in kd.sql("SELECT id FROM entities WHERE run_id = 1")["id"].to_pylist()
        }
        assert kd.get_tile("subsystem", 0, 0)["elevation"][0, 0] == 2  # run 1's map
        assert kd.run_filter("e") == "e.run_id = 1"
    with kd_store.open(path, read_only=True, run=0) as kd:  # an earlier run, whole
        assert kd.run_id == 0
        assert {f.id for f in kd.entities()} == set(
            kd.sql("SELECT id FROM entities WHERE run_id = 0")["id"].to_pylist()
        )
        assert kd.get_tile("subsystem", 0, 0)["elevation"][0, 0] == 1
    assert check_file(path).ok


def test_continuing_the_newest_run_keeps_its_frames_and_map(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    _two_runs(path)
    with kd_store.open(path) as kd:  # "latest": run 1 again, its frames in memory
        assert kd.run_id == 1 and len(list(kd.entities())) > 0
        kd.add_entity("late", 4, status="confirmed", confidence=1.0)
    with kd_store.open(path, read_only=True) as kd:
        rows = kd.sql("SELECT run_id FROM entities WHERE name = 'late'")["run_id"].to_pylist()
        assert rows == [1]
        assert kd.sql("SELECT count(*) AS n FROM runs")["n"][0].as_py() == 2


@pytest.mark.parametrize(
    ("run", "read_only", "match"),
    [
        (5, True, r"run 5 is not in the file \(its runs: \[0, 1\]\)"),
        ("new", True, "a new run needs the file open for writing"),
        ("next", False, "run 'next': give 'latest', 'new' or a run id"),
        (True, True, "run True: give"),
    ],
)
def test_a_run_that_cannot_be_opened_is_named(
    tmp_path: Path, run: object, read_only: bool, match: str
) -> None:
    path = tmp_path / "kd.duckdb"
    _two_runs(path)
    with pytest.raises(KDError, match=match):
        kd_store.open(path, read_only=read_only, run=run)  # type: ignore[arg-type]


def _as_version_2(path: Path) -> None:
    """Make ``path`` what schema version 2 wrote: no run_rows, no run_id columns, no fitted
    prototypes."""
    con = duckdb.connect(str(path))
    con.execute("DROP VIEW classes")
    con.execute("ALTER TABLE class_prototypes DROP COLUMN fitted")
    con.execute("DROP VIEW runs")
    con.execute("DROP TABLE run_rows")
    for view in VIEWS:  # version 2's views had no run_id; the migration makes them again
        con.execute(f"DROP VIEW {view}")
    for table in RUN_TABLES:
        con.execute(f"ALTER TABLE {table} DROP COLUMN run_id")
    con.execute("UPDATE kd_meta SET value = '2' WHERE key = 'schema_version'")
    con.close()


def test_a_version_2_file_is_read_as_run_0_and_migrated(tmp_path: Path) -> None:
    path = tmp_path / "old.duckdb"
    with kd_store.open(path) as kd:
        ids = build_full_kd(kd)
        kd.put_tile("subsystem", 1, 2, {"a": np.ones(3)})
    _as_version_2(path)
    with kd_store.open(path, read_only=True) as kd:  # as it is: everything, run 0
        assert kd.run_id == 0 and kd.run_filter() == "TRUE"
        assert {f.id for f in kd.entities()} >= {ids["tree"]}
        assert kd.tile_keys() == [("subsystem", 1, 2)]
    with pytest.raises(KDError, match="holds run 0 only"):
        kd_store.open(path, read_only=True, run=1)
    with kd_store.open(path, run="new", source="after.mcap") as kd:  # migrated, then run 1
        assert kd.run_id == 1 and list(kd.entities()) == []
    with kd_store.open(path, read_only=True, run=0) as kd:
        version = kd.sql("SELECT value FROM kd_meta WHERE key = 'schema_version'")
        assert int(version["value"][0].as_py()) == SCHEMA_VERSION == 4
        assert kd.sql("SELECT count(*) AS n FROM classes WHERE fitted")["n"][0].as_py() == 0
        runs = kd.sql("SELECT run_id, source FROM runs ORDER BY run_id").to_pylist()
        assert runs == [
            {"run_id": 0, "source": "written by schema version 2"},
            {"run_id": 1, "source": "after.mcap"},
        ]
        assert {f.id for f in kd.entities()} >= {ids["tree"]}
        assert kd.get_tile("subsystem", 1, 2)["a"].tolist() == [1, 1, 1]
        n_other = kd.sql("SELECT count(*) AS n FROM entities WHERE run_id <> 0")["n"][0]
        assert n_other.as_py() == 0
    assert check_file(path).ok


def test_the_check_finds_rows_of_unknown_or_mixed_runs(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    ids0, _ = _two_runs(path)
    con = duckdb.connect(str(path))
    con.execute(f"UPDATE entity_state_rows SET run_id = 7 WHERE entity_id = {ids0['tree']}")
    con.close()
    result = check_file(path)
    kinds = {(d.kind, d.table): d for d in result.defects}
    assert kinds[("unknown_run", "entity_state_rows")].ids == (7,)
    assert kinds[("run_mismatch", "entity_state_rows")].ids == (ids0["tree"],)
    assert len(result.defects) == 2, [d.text() for d in result.defects]
    assert result.counts["run_rows"] == 2
