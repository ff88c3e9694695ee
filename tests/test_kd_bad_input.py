"""Bad input is refused with a KDError that names the value and the frame, and nothing of
the refused call stays behind."""

from __future__ import annotations

import numpy as np
import pytest

import kd_store
from kd_store import KDError, Level, State, StateBatch


@pytest.fixture
def kd() -> kd_store.KnowledgeDatabase:
    kd = kd_store.open()
    for i in range(3):
        kd.add_entity(f"e{i}", Level.OBJECT, id=i, state=State(100, "world", (i, 0.0, 0.0)))
    return kd


def _fingerprint(kd: kd_store.KnowledgeDatabase) -> tuple:
    return (
        [kd.get(i).state for i in range(3)],
        [len(kd.history(i)) for i in range(3)],
        sorted((r.key, r.t_to_ns) for i in range(3) for r in kd.relations(i)),
        kd.entity_ids().tolist(),
    )


def _batch(ids: list[int], ts: list[int], **arrays: np.ndarray) -> StateBatch:
    n = len(ids)
    return StateBatch(
        np.array(ids), np.array(ts), "world", arrays.pop("pos", np.zeros((n, 3))), **arrays
    )


def test_unknown_ids(kd: kd_store.KnowledgeDatabase) -> None:
    before = _fingerprint(kd)
    with pytest.raises(KDError, match=r"entity 42: unknown id"):
        kd.get(42)
    with pytest.raises(KDError, match=r"event 42"):
        kd.get_event(42)
    with pytest.raises(KDError, match=r"entities \[7\] are not in the KD"):
        kd.ingest(_batch([0, 7], [200, 200]))
    with pytest.raises(KDError, match=r"frame 9 is not in the KD"):
        kd.relate(0, "near", 9)
    with pytest.raises(KDError, match=r"class pointer 'unicorn'"):
        kd.update_entity(0, generic_classes=("unicorn",))
    assert _fingerprint(kd) == before


def test_belongs_to_cycle(kd: kd_store.KnowledgeDatabase) -> None:
    kd.relate(0, "belongs_to", 1)
    kd.relate(1, "belongs_to", 2)
    before = _fingerprint(kd)
    with pytest.raises(KDError, match=r"relation 2 belongs_to 0: frame 2 is already an ancestor"):
        kd.relate(2, "belongs_to", 0)
    with pytest.raises(KDError, match=r"relation 0 has_part 2"):
        kd.relate(0, "has_part", 2)
    with pytest.raises(KDError, match=r"cannot point to itself"):
        kd.relate(1, "near", 1)
    assert _fingerprint(kd) == before


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("pos", np.array([[0.0, np.nan, 0.0]]), "position_xyz is not finite"),
        ("velocity_xyz", np.array([[np.inf, 0.0, 0.0]]), "velocity_xyz is not finite"),
        ("orientation_xyzw", np.array([[0.0, 0.0, 0.0, 2.0]]), "not a unit quaternion"),
        ("orientation_var_rpy", np.array([[0.0, -1.0, 0.0]]), "negative orientation_var_rpy"),
        (
            "covariance",
            np.diag([1.0, 1, 1, 1, 1, -0.5])[None],
            "covariance is not positive semidefinite",
        ),
        ("covariance", np.triu(np.ones((6, 6)))[None], "covariance is not symmetric"),
        ("covariance", np.full((1, 6, 6), np.nan), "covariance is not finite"),
    ],
)
def test_bad_state_values(
    kd: kd_store.KnowledgeDatabase, field: str, value: np.ndarray, message: str
) -> None:
    before = _fingerprint(kd)
    with pytest.raises(KDError, match=rf"entity 1 at t_ns=200: {message}"):
        kd.ingest(_batch([1], [200], **{field: value}))
    single = {"pos": "position_xyz"}.get(field, field)
    state = State(200, "world", (0, 0, 0))
    kwargs = {
        k: getattr(state, k)
        for k in ("position_xyz", "orientation_xyzw", "velocity_xyz", "covariance")
    }
    kwargs["orientation_var_rpy"] = state.orientation_var_rpy
    kwargs[single] = value[0]
    with pytest.raises(KDError, match=r"entity 1 \('e1'\)"):
        kd.observe(1, State(200, "world", **kwargs))
    assert _fingerprint(kd) == before


def test_psd_check_matches_eigenvalues() -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(2000, 6, 6))
    C = A @ A.transpose(0, 2, 1) - rng.uniform(0, 2, (2000, 1, 1)) * np.eye(6)
    truth = np.linalg.eigvalsh(C)[:, 0] >= -1e-9 * np.maximum(1, np.abs(C).max(axis=(1, 2)))
    from kd_store.covariance import pack_covariance, psd_mask

    got = psd_mask(pack_covariance(C))
    margin = np.abs(np.linalg.eigvalsh(C)[:, 0]) > 1e-6  # away from the tolerance edge
    assert truth[margin].any() and (~truth[margin]).any()
    np.testing.assert_array_equal(got[margin], truth[margin])


def test_time_going_backwards(kd: kd_store.KnowledgeDatabase) -> None:
    before = _fingerprint(kd)
    with pytest.raises(KDError, match=r"entity 2: t_ns=50 goes back from its current state"):
        kd.ingest(_batch([0, 2], [200, 50]))
    with pytest.raises(KDError, match=r"entity 1: t_ns=300 does not come after t_ns=300"):
        kd.ingest(_batch([1, 1], [300, 300]))
    with pytest.raises(KDError, match=r"entity 0: t_ns=100 goes back"):
        kd.observe(0, State(100, "world", (5.0, 0, 0)))
    assert _fingerprint(kd) == before
    kd.ingest(_batch([1, 1], [400, 300]))  # out of order inside a batch is fine
    assert [s.t_ns for s in kd.history(1)] == [100, 300, 400]


def test_bad_frame_fields(kd: kd_store.KnowledgeDatabase) -> None:
    n = len(kd.entity_ids())
    with pytest.raises(KDError, match=r"new entity 'x': confidence 1.5 is not in \[0, 1\]"):
        kd.add_entity("x", Level.OBJECT, confidence=1.5)
    with pytest.raises(KDError, match=r"id 1 is already taken"):
        kd.add_entity("x", Level.OBJECT, id=1)
    with pytest.raises(KDError, match=r"event 9 \('late'\): t_end_ns 5 is before t_start_ns 10"):
        kd.add_event("late", "c", 10, t_end_ns=5, id=9)
    with pytest.raises(KDError, match=r"involves points from an event to an entity"):
        kd.relate(0, "involves", 1)
    with pytest.raises(KDError, match=r"unknown relation kind"):
        kd.relate(0, "loves", 1)
    with pytest.raises(KDError, match=r"expectation at t_ns=50 is not after"):
        kd.expect(0, [State(50, "world", (0, 0, 0))])
    assert len(kd.entity_ids()) == n and 9 not in kd
