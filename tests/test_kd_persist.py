"""Round trips of every field through memory, a DuckDB file and Parquet; schema versions;
read-only SQL over the documented views."""

from __future__ import annotations

import math
from pathlib import Path

import duckdb
import numpy as np
import pytest

import kd_store
from kd_store import Attribute, KDError, Level, RelationKind, State, Status, Value
from kd_store.persist import SCHEMA_VERSION


def _cov(seed: int) -> np.ndarray:
    A = np.random.default_rng(seed).normal(size=(6, 4))
    return A @ A.T  # PSD of rank 4


def _state(t_ns: int, seed: int, frame: str = "world") -> State:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    return State(
        t_ns,
        frame,
        rng.normal(size=3) * 10,
        q / np.linalg.norm(q),
        rng.normal(size=3),
        _cov(seed),
        rng.uniform(0, 0.1, 3),
    )


def build_full_kd(kd: kd_store.KnowledgeDatabase) -> dict[str, int]:
    """A KD using every field of every frame kind; returns the ids by role."""
    tree = kd.add_entity(
        "oak-7",
        Level.OBJECT,
        status=Status.CONFIRMED,
        confidence=0.875,
        name_uncertainty=0.125,
        attributes={
            "height_m": Attribute(7.5, 0.25, 7.25, 0.0625, 7.3, 0.1),
            "width_m": Attribute(estimated=3.0, estimated_var=0.5),  # others NaN
        },
        state=_state(1_000, 1),
        generic_classes=("vegetation", "tree"),
        value=Value(0.5, 0.25, 0.125, 0.0625, 2.0, 3.5),
        images=("object_image/level4",),
        map_cells=((3, 128, 127), (4, 12, 13)),
        created_ns=999,
        noteworthy=False,
    )
    kd.observe(tree.id, _state(2_000, 2))
    kd.expect(tree.id, [_state(3_000, 3), _state(4_000, 4, "world")])
    kd.found_specific_class(tree.id)
    trunk = kd.add_entity(
        "trunk", Level.SURFACE, status="confirmed", confidence=0.7, state=_state(1_500, 5)
    )
    kd.relate(trunk.id, RelationKind.BELONGS_TO, tree.id, t_ns=1_500)
    post = kd.add_entity("post-1", 4, generic_classes=("post",), noteworthy=True)
    kd.relate(post.id, "beside", tree.id, t_ns=100)
    kd.unrelate(post.id, "beside", tree.id, t_ns=900)
    kd.relate(post.id, "near", tree.id, t_ns=900)
    ev = kd.add_event(
        "passed oak",
        "landmark_passed",
        1_000,
        t_end_ns=5_000,
        attributes={"closest_m": 4.5, "speed_mps": 2.0},
        level=3,
        confidence=0.9,
        name_uncertainty=0.2,
        value=Value(cost=1.0, risk=0.5),
    )
    sub = kd.add_event("saw oak", "detection", 1_000, t_end_ns=1_200, confidence=0.95)
    kd.relate(sub.id, "belongs_to", ev.id, t_ns=1_000)
    kd.relate(ev.id, "involves", tree.id, t_ns=1_000)
    kd.relate(sub.id, "before", ev.id, t_ns=1_200)
    kd.relate(sub.id, "causes", ev.id, t_ns=1_200)
    return {"tree": tree.id, "trunk": trunk.id, "post": post.id, "event": ev.id, "sub": sub.id}


def snapshot(kd: kd_store.KnowledgeDatabase, ids: dict[str, int]) -> dict:
    """Everything a round trip must keep, in comparable form."""
    return {
        "entities": {k: kd.get(ids[k]) for k in ("tree", "trunk", "post")},
        "events": {k: kd.get_event(ids[k]) for k in ("event", "sub")},
        "relations": sorted((r.key, r.t_to_ns) for i in ids.values() for r in kd.relations(i)),
        "classes": {p.name: p for p in kd.classes},
        "next": kd.next_id,
    }


def test_every_field_survives_memory(tmp_path: Path) -> None:
    kd = kd_store.open()
    ids = build_full_kd(kd)
    f = kd.get(ids["tree"])
    assert f.name == "oak-7" and f.level == Level.OBJECT and f.status == Status.CONFIRMED
    assert f.confidence == 0.875 and f.name_uncertainty == 0.125
    assert f.state == _state(2_000, 2)
    assert f.expectations == (_state(3_000, 3), _state(4_000, 4))
    assert f.attributes["height_m"] == Attribute(7.5, 0.25, 7.25, 0.0625, 7.3, 0.1)
    assert math.isnan(f.attributes["width_m"].observed)
    assert f.specific_class == f"oak-7#{f.id}"
    assert f.value == Value(0.5, 0.25, 0.125, 0.0625, 2.0, 3.5)
    assert f.map_cells == ((3, 128, 127), (4, 12, 13)) and f.created_ns == 999
    assert kd.history(ids["tree"]) == [_state(1_000, 1), _state(2_000, 2)]


def test_every_field_survives_a_duckdb_file(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    with kd_store.open(path) as kd:
        ids = build_full_kd(kd)
        before = snapshot(kd, ids)
    with kd_store.open(path) as kd:
        after = snapshot(kd, ids)
        assert kd.long_term_history(ids["tree"]) == [_state(1_000, 1), _state(2_000, 2)]
    assert after == before


def test_every_field_survives_parquet(tmp_path: Path) -> None:
    kd = kd_store.open()
    ids = build_full_kd(kd)
    before = snapshot(kd, ids)
    files = kd.export_parquet(tmp_path / "pq")
    assert {p.name for p in files} >= {"entity_frames.parquet", "entity_state_rows.parquet"}
    kd2 = kd_store.open()
    kd2.import_parquet(tmp_path / "pq")
    assert snapshot(kd2, ids) == before
    assert kd2.long_term_history(ids["tree"]) == [_state(1_000, 1), _state(2_000, 2)]
    with pytest.raises(KDError, match="already holds"):
        kd2.import_parquet(tmp_path / "pq")


def test_newer_schema_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    kd_store.open(path).close()
    con = duckdb.connect(str(path))
    con.execute("UPDATE kd_meta SET value = '99' WHERE key = 'schema_version'")
    con.close()
    newer = rf"schema version 99 is newer than this engine's {SCHEMA_VERSION}"
    with pytest.raises(KDError, match=newer):
        kd_store.open(path)


def test_sql_views_and_read_only() -> None:
    kd = kd_store.open()
    ids = build_full_kd(kd)
    t = kd.sql("SELECT id, class_name, x FROM entities ORDER BY id")
    assert t.column("id").to_pylist() == sorted([ids["tree"], ids["trunk"], ids["post"]])
    rel = kd.sql(
        f"SELECT kind, dst_id, dst_name, t_to_ns FROM relations WHERE src_id = {ids['post']} "
        "ORDER BY t_from_ns, kind"
    ).to_pylist()
    assert {"kind": "beside", "dst_id": ids["tree"], "dst_name": None, "t_to_ns": 900} in rel
    assert {"kind": "is_a", "dst_id": None, "dst_name": "post", "t_to_ns": None} in rel
    attrs = kd.sql("SELECT name, estimated FROM entity_attributes ORDER BY name").to_pylist()
    assert attrs == [{"name": "height_m", "estimated": 7.25}, {"name": "width_m", "estimated": 3.0}]
    at = kd.sql("SELECT entity_id, t_ns FROM entity_states_as_of(1600) ORDER BY entity_id")
    assert at.to_pylist() == [
        {"entity_id": ids["tree"], "t_ns": 1_000},
        {"entity_id": ids["trunk"], "t_ns": 1_500},
    ]
    ev = kd.sql("SELECT id FROM events_at(1100) ORDER BY id").column("id").to_pylist()
    assert ev == [ids["event"], ids["sub"]]
    assert kd.sql("SELECT count(*) AS n FROM classes WHERE kind = 'specific'")["n"][0].as_py() == 1
    for bad in ("DELETE FROM entity_frames", "SELECT 1; DROP TABLE entity_frames", "COPY x TO 'y'"):
        with pytest.raises(KDError, match="read-only SELECT"):
            kd.sql(bad)
    assert kd.sql("SELECT count(*) AS n FROM entities")["n"][0].as_py() == 3


def test_checkpoint_context_manager_and_read_only(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    with kd_store.open(path) as kd:
        a = kd.add_entity("a", Level.OBJECT, status="confirmed", confidence=1.0)
        kd.observe(a.id, _state(10, 1))
        assert kd.checkpoint() == 1
        wal = Path(str(path) + ".wal")
        assert not wal.exists() or wal.stat().st_size == 0
        b = kd.add_entity("b", Level.OBJECT, status="confirmed", confidence=1.0)
    # the clean exit flushed b
    with kd_store.open(path, read_only=True) as kd:
        assert [f.name for f in kd.entities()] == ["a", "b"]
        kd.update_entity(b.id, confidence=0.5)  # stays in RAM
        assert kd.flush() == 0
    with kd_store.open(path) as kd:
        assert kd.get(b.id).confidence == 1.0
    with pytest.raises(KDError, match=r"none\.duckdb: cannot open"):
        kd_store.open(tmp_path / "none.duckdb", read_only=True)
    duckdb.connect(str(tmp_path / "other.duckdb")).execute("CREATE TABLE t (a INT)").close()
    with pytest.raises(KDError, match=r"other\.duckdb: not a KD file"):
        kd_store.open(tmp_path / "other.duckdb", read_only=True)


def _tables(con: duckdb.DuckDBPyConnection) -> dict[str, str]:
    """Every base table's rows in a fixed order, as text (NaN compares equal so)."""
    out = {}
    for table in kd_store.persist.TABLES:
        if table == "run_rows":  # its start time is the wall clock's
            continue
        cols = [r[0] for r in con.execute(f"DESCRIBE {table}").fetchall()]
        order = ", ".join(f'"{c}"' for c in cols if c not in ("attributes", "weights", "data"))
        out[table] = repr(con.execute(f"SELECT * FROM {table} ORDER BY {order}").fetchall())
    return out


def test_staged_rows_keep_the_file_and_rebuild_it_elsewhere(tmp_path: Path) -> None:
    """Changes collected in steps (``stage``, as a live node serving SQL does each cycle) and
    written by the next flush, merged in one transaction, leave the file as one flush of them
    all does; the same rows, handed to ``on_rows`` in order, written over a copy of the file
    taken before them rebuild it: the KD as of the last stage (a replica, wm.serve_sql)."""
    from kd_store import persist

    staged = kd_store.open(tmp_path / "staged.duckdb")
    plain = kd_store.open(tmp_path / "plain.duckdb")
    for kd in (staged, plain):
        build_full_kd(kd)
        kd.flush()
    staged.copy_committed(tmp_path / "replica.duckdb")
    shipped: list[persist.Rows] = []
    staged.on_rows = shipped.append

    def change(kd: kd_store.KnowledgeDatabase, k: int) -> None:
        tree = next(f.id for f in kd.entities() if f.name == "oak-7")
        kd.observe(tree, _state(5_000 + 100 * k, 10 + k))
        kd.update_entity(tree, confidence=0.5 + 0.1 * k, map_cells=((4, k, k),))
        kd.expect(tree, [_state(9_000 + 100 * k, 20 + k)])
        kd.add_entity(f"new-{k}", Level.OBJECT, noteworthy=True, state=_state(5_000, 30 + k))
        kd.put_tile("subsystem", k % 2, 0, {"elevation": np.full((4, 4), k, np.float32)})

    for k in range(4):
        change(staged, k)
        change(plain, k)
        staged.stage()
    assert len(staged.unflushed) == 4 and len(shipped) == 4
    assert all(r.tiles is None for r in shipped)  # tiles go with the file's own writes
    replica = persist.connect(tmp_path / "replica.duckdb")
    for rows in shipped:  # one at a time, as a server applies each cycle's changes
        persist.write_rows(replica, rows)
    staged_file = staged._con  # before the flush: the file lacks what was staged
    assert _tables(staged_file)["entity_state_rows"] != _tables(replica)["entity_state_rows"]
    assert staged.flush() > 0 and plain.flush() > 0
    assert staged.unflushed == [] and shipped[-1].tiles is not None  # the flush's own rows
    persist.write_rows(replica, shipped[-1])
    assert _tables(staged._con) == _tables(plain._con) == _tables(replica)
    merged = persist.merge_rows(shipped)
    assert merged.state_rows == sum(r.state_rows for r in shipped)
    for kd in (staged, plain):
        kd.close()
    replica.close()
