"""update_entity re-checks only what it changes: fields are still refused, and expectations
given anew are checked as before (the kept state and queue were checked when they came in)."""

from __future__ import annotations

import numpy as np
import pytest

import kd_store
from kd_store import Attribute, KDError, Level, State


def _kd_with_entity() -> tuple[kd_store.KnowledgeDatabase, int]:
    kd = kd_store.open()
    kd.begin_cycle(0)
    e = kd.add_entity("rock", Level.OBJECT, generic_classes=("rock",))
    kd.observe(e.id, State(0, "world", (1.0, 2.0, 0.0), covariance=np.eye(6)))
    kd.expect(e.id, [State(t, "world", (1.0, 2.0, 0.0)) for t in (10, 20)])
    return kd, e.id


def test_update_keeps_state_and_queue_and_changes_the_field() -> None:
    kd, i = _kd_with_entity()
    before = kd.get(i)
    after = kd.update_entity(i, confidence=0.75)
    assert after.confidence == 0.75
    assert after.state is before.state
    assert after.expectations is before.expectations
    assert [s.t_ns for s in kd.get(i).expectations] == [10, 20]


@pytest.mark.parametrize(
    "changes",
    [
        {"confidence": 1.5},
        {"name_uncertainty": -0.1},
        {"attributes": {"length_m": Attribute(estimated=float("inf"))}},
        {"attributes": {"length_m": Attribute(estimated=1.0, estimated_var=-1.0)}},
    ],
)
def test_update_still_refuses_bad_fields(changes: dict) -> None:
    kd, i = _kd_with_entity()
    with pytest.raises(KDError, match=f"entity {i}"):
        kd.update_entity(i, **changes)
    assert kd.get(i).confidence != 1.5


def test_update_checks_new_expectations() -> None:
    kd, i = _kd_with_entity()
    bad_cov = -np.eye(6)
    with pytest.raises(KDError, match="positive semidefinite"):
        kd.update_entity(i, expectations=(State(30, "world", (0, 0, 0), covariance=bad_cov),))
    with pytest.raises(KDError, match="not after"):
        kd.update_entity(i, expectations=(State(0, "world", (0, 0, 0)),))  # not after the state
    kd.update_entity(i, expectations=(State(40, "world", (0, 0, 0)),))
    assert [s.t_ns for s in kd.get(i).expectations] == [40]
