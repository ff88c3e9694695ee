"""Memory tiers and queries: as-of against a hand-computed history, short-term horizons and
forgetting, promotion rules, immediate experience, region queries against brute force."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import kd_store
from kd_store import (
    Box,
    Circle,
    KDConfig,
    Level,
    MemoryConfig,
    PromotionRule,
    State,
    StateBatch,
    Status,
    Value,
)

#: Horizons of 10, 20, 30 and 100 ns keep the hand-computed histories short.
TINY = MemoryConfig(
    horizons_s={"primitive": 1e-8, "subsystem": 2e-8, "vehicle": 3e-8, "section": 1e-7}
)


def _x(states: dict[int, State]) -> dict[int, float]:
    return {k: float(s.position_xyz[0]) for k, s in states.items()}


def _history_kd(path: str = ":memory:") -> kd_store.KnowledgeDatabase:
    """A: x=1 at t=10, 2 at 20, 3 at 30. B: x=10 at 15, 20 at 25 (one batch, mixed order)."""
    kd = kd_store.open(path)
    kd.add_entity("A", Level.OBJECT, id=0, status="confirmed", confidence=1.0)
    kd.add_entity("B", Level.OBJECT, id=1, status="confirmed", confidence=1.0)
    ids, ts, xs = [1, 0, 0, 1, 0], [25, 20, 10, 15, 30], [20.0, 2.0, 1.0, 10.0, 3.0]
    pos = np.zeros((5, 3))
    pos[:, 0] = xs
    kd.ingest(StateBatch(np.array(ids), np.array(ts), "world", pos))
    return kd


def test_as_of_matches_the_hand_computed_history() -> None:
    kd = _history_kd()
    expected = {
        5: {},
        10: {0: 1.0},
        14: {0: 1.0},
        15: {0: 1.0, 1: 10.0},
        22: {0: 2.0, 1: 10.0},
        25: {0: 2.0, 1: 20.0},
        100: {0: 3.0, 1: 20.0},
    }
    for t, want in expected.items():
        assert _x(kd.as_of(t)) == want, t
        sql = kd.sql(f"SELECT entity_id, x FROM entity_states_as_of({t}) ORDER BY entity_id")
        assert dict(zip(*sql.to_pydict().values(), strict=True)) == want, t
    assert float(kd.get(0).state.position_xyz[0]) == 3.0
    assert [s.t_ns for s in kd.history(0)] == [10, 20, 30]


def test_short_term_memory_keeps_one_horizon_and_forgets() -> None:
    kd = kd_store.open(config=KDConfig(memory=TINY))
    obj = kd.add_entity("obj", Level.OBJECT, id=0)  # vehicle level: 30 ns
    pt = kd.add_entity("pt", Level.POINT, id=1)  # primitive level: 10 ns
    kept = kd.add_entity("kept", Level.POINT, id=2)
    kd.set_attention("primitive", [kept.id])
    for t in range(10, 60, 10):
        kd.ingest(StateBatch(np.array([0, 1, 2]), np.full(3, t), "world", np.full((3, 3), t)))
    kd.advance(50)
    assert [s.t_ns for s in kd.history(obj.id)] == [20, 30, 40, 50]
    assert [s.t_ns for s in kd.history(pt.id)] == [40, 50]
    assert kd.advance(75) == [pt.id]  # last seen at 50 < 75 - 10; obj within 30 ns
    assert pt.id not in kd and kept.id in kd and obj.id in kd
    assert kd.advance(200) == [obj.id]
    assert kd.entity_ids().tolist() == [kept.id]


def test_promotion_rules(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    kd = kd_store.open(path, KDConfig(memory=TINY))
    hyp = kd.add_entity("hyp", Level.OBJECT, confidence=0.9)
    kd.add_entity("conf", Level.OBJECT, status=Status.CONFIRMED, confidence=0.9)
    weak = kd.add_entity("weak", Level.OBJECT, status=Status.CONFIRMED, confidence=0.3)
    note = kd.add_entity("note", Level.OBJECT, status=Status.DENIED)
    kd.add_entity("rich", Level.OBJECT, value=Value(worth_defend=0.8))
    quiet = kd.add_event("quiet", "c", 0, t_end_ns=1, confidence=0.1)
    kd.add_event("loud", "c", 0, t_end_ns=1, confidence=0.8)
    kd.mark_noteworthy(note.id)

    def stored() -> set[str]:
        return set(
            kd.sql("SELECT name FROM entities UNION ALL SELECT name FROM events")[
                "name"
            ].to_pylist()
        )

    assert stored() == {"conf", "note", "loud"}
    kd.promotion_rule = PromotionRule(min_worth=0.5, min_event_confidence=0.05)  # set by VJ
    assert stored() == {"conf", "note", "loud", "rich", "quiet"}
    kd.promotion_rule = PromotionRule(statuses=frozenset({"confirmed", "hypothesized"}))
    kd.update_entity(weak.id, confidence=0.6)
    assert stored() == {"conf", "note", "loud", "rich", "quiet", "weak", "hyp"}
    kd.close()
    # long-term memory survives a restart; short-term-only frames do not exist there
    kd = kd_store.open(path, KDConfig(memory=TINY))
    assert {f.name for f in kd.entities()} == {"conf", "note", "rich", "weak", "hyp"}
    assert kd.advance(10**12) == []  # long-term frames are never forgotten
    assert hyp.id in kd and quiet.id in kd


def test_a_confirmation_is_remembered_though_the_track_fades_before_the_flush(
    tmp_path: Path,
) -> None:
    """A track confirmed and fading below the rule's confidence before the next flush (a car
    that drove out of view) was confirmed: long-term memory holds it. One never confirmed
    does not get there."""
    path = tmp_path / "kd.duckdb"
    kd = kd_store.open(path)
    car = kd.add_entity("car", Level.OBJECT, confidence=0.4)
    ghost = kd.add_entity("ghost", Level.OBJECT, confidence=0.4)
    kd.update_entity(car.id, status=Status.CONFIRMED, confidence=0.8)
    kd.update_entity(car.id, confidence=0.01)
    kd.update_entity(ghost.id, confidence=0.01)
    kd.flush()
    kd.close()
    with kd_store.open(path, read_only=True) as kd:
        rows = kd.sql("SELECT name, status, confidence FROM entities").to_pylist()
    assert rows == [{"name": "car", "status": "confirmed", "confidence": 0.01}]


def test_only_promoted_states_reach_long_term_memory() -> None:
    kd = kd_store.open()
    a = kd.add_entity("a", Level.OBJECT, status="confirmed", confidence=0.9)
    b = kd.add_entity("b", Level.OBJECT)
    kd.ingest(StateBatch(np.array([a.id, b.id]), np.array([1, 1]), "world", np.zeros((2, 3))))
    kd.flush()
    kd.ingest(StateBatch(np.array([a.id, b.id]), np.array([2, 2]), "world", np.ones((2, 3))))
    kd.update_entity(b.id, status=Status.CONFIRMED, confidence=0.7)  # promoted with history
    rows = kd.sql("SELECT entity_id, t_ns FROM entity_states ORDER BY ALL").to_pylist()
    assert rows == [
        {"entity_id": a.id, "t_ns": 1},
        {"entity_id": a.id, "t_ns": 2},
        {"entity_id": b.id, "t_ns": 1},
        {"entity_id": b.id, "t_ns": 2},
    ]
    assert kd.flush() == 0  # nothing new


def test_immediate_experience_is_this_cycle() -> None:
    kd = kd_store.open()
    for i in range(4):
        kd.add_entity(f"e{i}", Level.OBJECT, id=i)
    kd.begin_cycle(100)
    kd.ingest(StateBatch(np.array([2, 0, 2]), np.array([100, 100, 90]), "world", np.zeros((3, 3))))
    new = kd.add_entity("new", Level.SURFACE, state=State(100, "world", (0, 0, 0)))
    assert kd.observed_this_cycle().tolist() == [0, 2, new.id]
    assert kd.get(new.id).created_ns == 100
    kd.begin_cycle(200)
    assert kd.observed_this_cycle().tolist() == []


def test_region_queries_match_brute_force() -> None:
    rng = np.random.default_rng(3)
    kd = kd_store.open(config=KDConfig(grid_cell_m=5.0))
    n = 3000
    classes = [None, "tree", "bush", "vehicle", "person", "road"]
    truth = []
    for i in range(n):
        cls = classes[i % len(classes)]
        status = list(Status)[i % 4]
        level = Level.SURFACE if cls == "road" else Level.OBJECT
        conf = float(rng.uniform())
        kd.add_entity(
            f"e{i}", level, id=i, status=status, confidence=conf,
            generic_classes=() if cls is None else (cls,),
        )  # fmt: skip
        truth.append((cls, status, level, conf))
    pos = rng.uniform(-100, 100, (n, 3))
    frames = np.where(np.arange(n) % 5 == 0, "odom", "world")
    for fr in ("world", "odom"):
        m = frames == fr
        kd.ingest(StateBatch(np.flatnonzero(m), np.ones(m.sum(), np.int64), fr, pos[m]))
    veg = {"tree", "bush"}
    for _ in range(40):
        c = rng.uniform(-90, 90, 2)
        r = float(rng.uniform(1, 40))
        lo = np.r_[c - r, -20.0]
        hi = np.r_[c + r, 30.0]
        min_conf = float(rng.uniform(0, 0.5))
        circle_in = np.hypot(*(pos[:, :2] - c).T) <= r
        box_in = np.all((pos >= lo) & (pos <= hi), axis=1)
        world = frames == "world"
        got = kd.region(Circle("world", tuple(c), r))
        assert got.tolist() == np.flatnonzero(circle_in & world).tolist()
        got = kd.region(Box("odom", tuple(lo), tuple(hi)), min_confidence=min_conf)
        conf_ok = np.array([t[3] >= min_conf for t in truth])
        assert got.tolist() == np.flatnonzero(box_in & ~world & conf_ok).tolist()
        got = kd.region(
            Circle("world", tuple(c), r), classes=["vegetation"], statuses=["confirmed"]
        )
        want = [
            i for i in np.flatnonzero(circle_in & world)
            if truth[i][0] in veg and truth[i][1] == Status.CONFIRMED
        ]  # fmt: skip
        assert got.tolist() == want
        got = kd.region(Circle("world", tuple(c), r), levels=[Level.SURFACE])
        want = [i for i in np.flatnonzero(circle_in & world) if truth[i][2] == Level.SURFACE]
        assert got.tolist() == want
    assert kd.region(Circle("map", (0.0, 0.0), 10.0)).tolist() == []
    with pytest.raises(kd_store.KDError, match="empty or not finite"):
        kd.region(Circle("world", (0.0, float("nan")), 1.0))


def _pose(yaw: float, roll: float, t_xyz: tuple[float, float, float]) -> np.ndarray:
    cy, sy, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(roll), np.sin(roll)
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rz @ Rx, t_xyz
    return T


def test_region_in_another_frame_matches_brute_force() -> None:
    rng = np.random.default_rng(5)
    kd = kd_store.open(config=KDConfig(grid_cell_m=4.0))
    n = 2000
    for i in range(n):
        kd.add_entity(f"e{i}", Level.OBJECT, id=i)
    pos = rng.uniform(-60, 60, (n, 3))
    world = np.arange(n) % 3 != 0
    kd.ingest(
        StateBatch(np.flatnonzero(world), np.ones(world.sum(), np.int64), "world", pos[world])
    )
    kd.ingest(
        StateBatch(np.flatnonzero(~world), np.ones((~world).sum(), np.int64), "odom", pos[~world])
    )
    poses = {"world": _pose(0.7, 0.0, (5.0, -3.0, 1.0)), "odom": _pose(-1.2, 0.2, (0.0, 4.0, 0.0))}
    p_body = np.where(
        world[:, None],
        pos @ poses["world"][:3, :3].T + poses["world"][:3, 3],
        pos @ poses["odom"][:3, :3].T + poses["odom"][:3, 3],
    )
    for _ in range(20):
        c, r = rng.uniform(-40, 40, 2), float(rng.uniform(2, 30))
        got = kd.region(Circle("base_link", tuple(c), r), poses=poses)
        want = np.flatnonzero(np.hypot(*(p_body[:, :2] - c).T) <= r)
        assert got.tolist() == want.tolist()
        box = Box("base_link", (c[0] - r, c[1] - r, -5.0), (c[0] + r, c[1] + r, 5.0))
        got = kd.region(box, poses={"world": poses["world"]})
        inside = np.all((p_body >= box.min_xyz) & (p_body <= box.max_xyz), axis=1)
        assert got.tolist() == np.flatnonzero(inside & world).tolist()


def test_as_of_reaches_into_long_term_memory_after_the_horizon() -> None:
    kd = kd_store.open(config=KDConfig(memory=TINY))  # vehicle level keeps 30 ns
    a = kd.add_entity("a", Level.OBJECT, status="confirmed", confidence=1.0)
    b = kd.add_entity("b", Level.OBJECT)  # short-term only
    for t in (10, 20, 30, 40, 100):
        kd.ingest(StateBatch(np.array([a.id, b.id]), np.array([t, t]), "world", np.full((2, 3), t)))
    kd.advance(100)  # short-term memory now holds t >= 70 only
    assert _x(kd.as_of(25)) == {}
    assert _x(kd.as_of(25, long_term=True)) == {a.id: 20.0}
    assert _x(kd.as_of(100, long_term=True)) == {a.id: 100.0, b.id: 100.0}
