"""Rules of level-4 classification and level-5 grouping, each on a case from physical facts:
extents as seen from one side, speed as an upper bound, physical bounds per class, and groups
that need moving members of a mobile class and earn their confirmation."""

from __future__ import annotations

import numpy as np

import kd_store
from kd_store import Level, Status
from sp.classify import Classifier
from sp.pipeline import SensoryProcessor


def _object_classifier() -> Classifier:
    return Classifier(kd_store.open(":memory:").classes, Level.OBJECT)


def _cls(c: Classifier, length: float, width: float, height: float, speed: float) -> str | None:
    row = {"length_m": length, "width_m": width, "height_m": height, "speed_mps": speed}
    return c.classify(row).name


def test_a_parked_car_seen_from_one_side_is_a_vehicle() -> None:
    c = _object_classifier()
    assert _cls(c, 4.2, 0.6, 1.5, 0.0) == "vehicle"  # long side, a thin L of points
    assert _cls(c, 4.0, 1.8, 1.45, 0.0) == "vehicle"  # seen from a corner
    assert _cls(c, 4.5, 1.9, 1.6, 8.0) == "vehicle"  # moving


def test_a_pole_is_not_a_person() -> None:
    c = _object_classifier()
    assert _cls(c, 0.2, 0.05, 3.0, 0.0) != "person"
    assert _cls(c, 0.2, 0.05, 1.8, 1.0) != "person"  # too thin, even if it seems to move


def test_a_person_needs_motion_and_a_person_sized_shape() -> None:
    c = _object_classifier()
    assert _cls(c, 0.6, 0.4, 1.75, 1.3) == "person"
    assert _cls(c, 0.6, 0.4, 1.75, 0.0) != "person"  # a still one is a trunk or a shrub
    assert _cls(c, 0.6, 0.4, 2.6, 1.3) != "person"  # taller than people are


def test_motion_is_evidence_against_static_classes_only() -> None:
    c = _object_classifier()
    still = c.classify({"length_m": 4.2, "width_m": 1.8, "height_m": 1.5, "speed_mps": 0.0})
    moving = c.classify({"length_m": 4.2, "width_m": 1.8, "height_m": 1.5, "speed_mps": 8.0})
    # stillness costs the vehicle nothing; motion costs the bush
    assert abs(still.scores["vehicle"] - moving.scores["vehicle"]) < 1e-9
    assert moving.scores["bush"] < still.scores["bush"]


def test_static_persons_make_no_convoy_and_groups_earn_confirmation() -> None:
    from sp.groups import GroupConfig, group_labels
    from sp.pipeline import MOBILE_CLASSES

    # the link rule the pipeline feeds: velocities of members not sure to move are zero
    xy = np.array([[0.0, 0.0], [3.0, 0.0], [6.0, 0.0]])
    still = np.zeros((3, 2))
    assert (group_labels(xy, still, np.zeros(3, bool), GroupConfig()) < 0).all()
    moving = np.tile([8.0, 0.0], (3, 1))
    assert (group_labels(xy, moving, np.zeros(3, bool), GroupConfig()) == 0).all()
    assert "vehicle" in MOBILE_CLASSES and "bush" not in MOBILE_CLASSES


def test_a_group_is_hypothesized_until_its_confidence_confirms_it() -> None:
    kd = kd_store.open(":memory:")
    sp = SensoryProcessor(kd)
    tc = sp.config.tracker
    gid = kd.add_entity("g", Level.GROUP, confidence=tc.confidence0).id
    members = frozenset(kd.add_entity(f"o{i}", Level.OBJECT).id for i in range(2))
    statuses = []
    for k in range(4):
        events: list[int] = []
        sp._group_confidence(gid, 1000 + k, members, events)
        sp.groups = {gid: members}
        statuses.append(kd.get(gid).status)
    assert statuses[0] == Status.HYPOTHESIZED  # a group seen once is not confirmed
    assert Status.CONFIRMED in statuses
    first = statuses.index(Status.CONFIRMED)
    assert first + 1 >= tc.min_hits
    assert kd.get(gid).confidence > tc.confirm
