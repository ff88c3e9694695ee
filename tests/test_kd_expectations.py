"""Short-term expectation queues: a new state drops the expectations it has overtaken (and
keeps the later ones), through observe, batch ingest, a flush and a reopen; expect() refuses
exactly what the state-by-state check refuses, naming the same state."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import kd_store
from kd_store import KDError, Level, State, StateBatch
from kd_store.frames import check_state


def _kd_with_queue(path: str = ":memory:") -> kd_store.KnowledgeDatabase:
    """Entity 0 (confirmed, so it reaches long-term memory): state at t=10, expectations at
    20, 30, 40 with x = t / 10."""
    kd = kd_store.open(path)
    kd.add_entity("car", Level.OBJECT, id=0, status="confirmed", confidence=1.0)
    kd.observe(0, State(10, "world", (1.0, 0.0, 0.0)))
    kd.expect(0, [State(t, "world", (t / 10, 0.0, 0.0)) for t in (20, 30, 40)])
    return kd


def _times(f: kd_store.EntityFrame) -> list[int]:
    return [s.t_ns for s in f.expectations]


def test_observe_drops_overtaken_expectations_and_keeps_later_ones() -> None:
    kd = _kd_with_queue()
    f = kd.observe(0, State(30, "world", (3.1, 0.0, 0.0)))
    assert f.state.t_ns == 30
    assert _times(f) == [40]  # 20 overtaken, 30 reached: history now
    assert f.expectations[0].position_xyz[0] == 4.0
    # the frame is whole again: changing it is accepted
    assert kd.update_entity(0, confidence=0.9).confidence == 0.9
    f = kd.observe(0, State(50, "world", (5.0, 0.0, 0.0)))
    assert _times(f) == []
    kd.expect(0, [State(60, "world", (6.0, 0.0, 0.0))])  # a new queue is taken
    assert _times(kd.get(0)) == [60]


def test_a_state_before_every_expectation_keeps_the_queue() -> None:
    kd = _kd_with_queue()
    assert _times(kd.observe(0, State(15, "world", (1.5, 0.0, 0.0)))) == [20, 30, 40]


def test_batch_ingest_drops_overtaken_expectations_per_entity(tmp_path: Path) -> None:
    path = str(tmp_path / "kd.duckdb")
    kd = _kd_with_queue(path)
    kd.add_entity("tree", Level.OBJECT, id=1, status="confirmed", confidence=1.0)
    kd.observe(1, State(10, "world", (0.0, 5.0, 0.0)))
    kd.expect(1, [State(t, "world", (0.0, 5.0, 0.0)) for t in (100, 200)])
    pos = np.zeros((3, 3))
    kd.ingest(StateBatch(np.array([0, 1, 0]), np.array([25, 150, 35]), "world", pos))
    assert _times(kd.get(0)) == [40]  # its last state in the batch (35) counts
    assert _times(kd.get(1)) == [200]
    kd.flush()
    kd.close()
    with kd_store.open(path) as kd:
        assert _times(kd.get(0)) == [40] and _times(kd.get(1)) == [200]
        rows = kd.sql("SELECT entity_id, t_ns FROM entity_expectations ORDER BY ALL")
        assert rows.to_pylist() == [{"entity_id": 0, "t_ns": 40}, {"entity_id": 1, "t_ns": 200}]
        kd.update_entity(0, confidence=0.5)  # reopened frames are whole


def test_a_refused_state_leaves_the_queue_alone() -> None:
    kd = _kd_with_queue()
    with pytest.raises(KDError, match="goes back"):
        kd.observe(0, State(5, "world", (0.0, 0.0, 0.0)))
    assert _times(kd.get(0)) == [20, 30, 40]


# ---------------------------------------------------------------- expect() refuses as before


def _cov(rng: np.random.Generator, min_eig: float) -> np.ndarray:
    """A symmetric 6x6 whose smallest eigenvalue is ``min_eig`` (others in [0.1, 2])."""
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    eig = np.r_[min_eig, rng.uniform(0.1, 2.0, 5)]
    C = (Q * eig) @ Q.T
    return 0.5 * (C + C.T)


BAD_KINDS = ("nan_position", "quaternion", "neg_var_rpy", "asymmetric", "not_psd", "time")


def _bad_state(kind: str, t: int, rng: np.random.Generator) -> State:
    if kind == "nan_position":
        return State(t, "world", (np.nan, 0.0, 0.0))
    if kind == "quaternion":
        return State(t, "world", (0, 0, 0), (0.0, 0.0, 0.1, 1.0))
    if kind == "neg_var_rpy":
        return State(t, "world", (0, 0, 0), orientation_var_rpy=(0.0, -1e-3, 0.0))
    if kind == "asymmetric":
        C = _cov(rng, 0.5)
        C[0, 5] += 1e-3
        return State(t, "world", (0, 0, 0), covariance=C)
    if kind == "not_psd":
        return State(t, "world", (0, 0, 0), covariance=_cov(rng, -1e-4))
    return State(5, "world", (0, 0, 0))  # "time": before the entity's state at t=10


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 30),
    where=st.integers(0, 29),
    kind=st.sampled_from(BAD_KINDS),
    seed=st.integers(0, 2**32 - 1),
)
def test_expect_refuses_what_the_state_check_refuses(n: int, where: int, kind: str, seed: int):
    """One bad state anywhere in a queue of good ones: refused, with the message the
    state-by-state check gives (or the time-order message), and the old queue kept."""
    rng = np.random.default_rng(seed)
    kd = _kd_with_queue()
    queue = [
        State(100 + 10 * i, "world", rng.normal(size=3), covariance=_cov(rng, 1e-3))
        for i in range(n)
    ]
    i = where % n
    queue[i] = _bad_state(kind, 100 + 10 * i, rng)
    with pytest.raises(KDError) as refused:
        kd.expect(0, queue)
    if kind == "time":
        assert "is not after the state before it" in str(refused.value)
    else:
        with pytest.raises(KDError) as one:
            check_state(queue[i], "entity 0 ('car') expectation")
        assert str(refused.value) == str(one.value)
    assert _times(kd.get(0)) == [20, 30, 40]


@settings(max_examples=30, deadline=None)
@given(
    min_eig=st.sampled_from([-1e-6, -2e-9, -5e-10, 0.0, 5e-10, 1e-6]),
    scale=st.sampled_from([1e-3, 1.0, 1e3]),
    seed=st.integers(0, 2**32 - 1),
)
def test_expect_accepts_exactly_the_covariances_the_state_check_accepts(
    min_eig: float, scale: float, seed: int
) -> None:
    """Near the tolerance edge (eigenvalue -tol * scale) the batched test agrees, state for
    state, with :func:`check_state`."""
    rng = np.random.default_rng(seed)
    states = [
        State(100 + i, "world", (0, 0, 0), covariance=scale * _cov(rng, min_eig)) for i in range(8)
    ]
    single = []
    for s in states:
        try:
            check_state(s, "probe")
            single.append(True)
        except KDError:
            single.append(False)
    kd = _kd_with_queue()
    for s, ok in zip(states, single, strict=True):
        if ok:
            kd.expect(0, [s])
        else:
            with pytest.raises(KDError):
                kd.expect(0, [s])
    try:
        kd.expect(0, states)
        batch_ok = True
    except KDError:
        batch_ok = False
    assert batch_ok == all(single)


def test_expect_refuses_what_is_not_a_state() -> None:
    kd = _kd_with_queue()
    with pytest.raises(KDError, match="is not a State"):
        kd.expect(0, [State(20, "world", (0, 0, 0)), (30, "world")])  # type: ignore[list-item]
