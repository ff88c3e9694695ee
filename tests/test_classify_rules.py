"""Rules of level-4 classification and level-5 grouping, each on a case from physical facts:
extents as seen from one side, speed as an upper bound, physical bounds per class, and groups
that need moving members of a mobile class and earn their confirmation."""

from __future__ import annotations

import numpy as np

import kd_store
from kd_store import Level, Status
from sp.classify import Classifier
from sp.computation import SegmentAttributes
from sp.pipeline import SPConfig
from wm.entities import KDSensoryProcessor


def _object_classifier() -> Classifier:
    """The written-down prototypes, whose rules these cases check (the fitted default is
    held to labelled tracks instead: tests/test_fit_classes.py)."""
    return Classifier(kd_store.ClassLibrary.default(fitted=False), Level.OBJECT)


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


def _shape(
    c: Classifier, lwh: tuple[float, float, float], speed: float, **shape: float
) -> str | None:
    """Class of an object of extents ``lwh`` (m), speed (m/s) and shape attributes of its
    points (sp.level4_objects.SHAPE_KEYS: thickness_m, verticality, breadth_m ...)."""
    row = {"length_m": lwh[0], "width_m": lwh[1], "height_m": lwh[2], "speed_mps": speed}
    return c.classify(row | shape).name


# a person's points in one sweep: an upright blob, 0.3-0.9 m across (std 0.1-0.26 m along the
# middle axis), a few centimetres off any plane (a curved torso, limbs)
PERSON_SHAPE = {"thickness_m": 0.05, "breadth_m": 0.13, "verticality": 0.25}


def test_a_person_is_a_person_sized_upright_blob_moving_or_not() -> None:
    c = _object_classifier()
    assert _shape(c, (0.6, 0.4, 1.75), 1.3, **PERSON_SHAPE) == "person"
    assert _shape(c, (0.6, 0.4, 1.75), 0.0, **PERSON_SHAPE) == "person"  # standing still
    assert _shape(c, (1.5, 0.45, 1.6), 1.2, **PERSON_SHAPE) == "person"  # the box trails a walker
    assert _shape(c, (0.6, 0.4, 2.6), 1.3, **PERSON_SHAPE) != "person"  # taller than people are


def test_a_wall_piece_of_person_height_is_not_a_person() -> None:
    c = _object_classifier()
    # 1.4 m of a wall: its points spread 0.4 m (std) along the middle axis, a plane
    piece = {"thickness_m": 0.01, "breadth_m": 0.4, "verticality": 0.02}
    assert _shape(c, (1.4, 0.3, 1.7), 0.0, **piece) != "person"


def test_a_planar_wall_piece_is_a_freestanding_wall_not_a_vehicle() -> None:
    c = _object_classifier()
    plane = {"thickness_m": 0.01, "breadth_m": 0.6, "verticality": 0.02}  # a vertical plane
    assert _shape(c, (5.0, 0.5, 2.0), 0.0, **plane) == "freestanding wall"
    assert _shape(c, (2.0, 0.4, 1.8), 0.0, **plane) == "freestanding wall"  # a short piece
    assert _shape(c, (12.0, 0.5, 2.2), 0.0, **plane) == "freestanding wall"
    # and a wall is a wall: its generic lineage names it
    assert "wall" in c.classify({"length_m": 5.0, "width_m": 0.5, "height_m": 2.0} | plane).generic


def test_a_car_seen_in_its_roof_and_side_is_still_a_vehicle() -> None:
    c = _object_classifier()
    # hood, roof and one side: a bent surface, mostly facing up
    car = {"thickness_m": 0.1, "breadth_m": 0.5, "verticality": 0.7}
    assert _shape(c, (4.2, 1.7, 1.5), 0.0, **car) == "vehicle"
    assert _shape(c, (4.2, 0.6, 1.5), 0.0, **car) == "vehicle"


def test_a_tree_crown_is_vegetation_not_a_vehicle() -> None:
    c = _object_classifier()
    crown = {"thickness_m": 0.45, "breadth_m": 0.8, "verticality": 0.4}  # a volume of leaves
    assert _shape(c, (4.0, 3.5, 6.0), 0.0, **crown) == "tree"
    assert _shape(c, (1.6, 1.4, 1.2), 0.0, **crown | {"breadth_m": 0.4}) == "bush"


def test_a_thin_pole_is_a_post() -> None:
    c = _object_classifier()
    pole = {"thickness_m": 0.005, "breadth_m": 0.03, "verticality": 0.02}
    assert _shape(c, (0.15, 0.15, 2.5), 0.0, **pole) == "post"
    assert _shape(c, (0.15, 0.12, 1.7), 0.0, **pole) == "post"  # person height, pole thin


def test_motion_is_evidence_against_static_classes_only() -> None:
    c = _object_classifier()
    still = c.classify({"length_m": 4.2, "width_m": 1.8, "height_m": 1.5, "speed_mps": 0.0})
    moving = c.classify({"length_m": 4.2, "width_m": 1.8, "height_m": 1.5, "speed_mps": 8.0})
    # stillness costs the vehicle nothing; motion costs the bush
    assert abs(still.scores["vehicle"] - moving.scores["vehicle"]) < 1e-9
    assert moving.scores["bush"] < still.scores["bush"]


def test_static_persons_make_no_convoy_and_groups_earn_confirmation() -> None:
    from sp.groups import GroupConfig, group_labels
    from sp.level5_groups import MOBILE_CLASSES

    # the link rule the pipeline feeds: velocities of members not sure to move are zero
    xy = np.array([[0.0, 0.0], [3.0, 0.0], [6.0, 0.0]])
    still = np.zeros((3, 2))
    assert (group_labels(xy, still, np.zeros(3, bool), GroupConfig()) < 0).all()
    moving = np.tile([8.0, 0.0], (3, 1))
    assert (group_labels(xy, moving, np.zeros(3, bool), GroupConfig()) == 0).all()
    assert "vehicle" in MOBILE_CLASSES and "bush" not in MOBILE_CLASSES


def test_a_group_is_hypothesized_until_its_confidence_confirms_it() -> None:
    kd = kd_store.open(":memory:")
    sp = KDSensoryProcessor(kd)
    tc = sp.config.tracker
    gid = kd.add_entity("g", Level.GROUP, confidence=tc.confidence0).id
    members = frozenset(kd.add_entity(f"o{i}", Level.OBJECT).id for i in range(2))
    # level 5 keeps its groups' status and confidence: the group as its frame was made
    sp.level5.frames[gid] = (Status.HYPOTHESIZED, tc.confidence0)
    statuses = []
    for k in range(4):
        events: list[int] = []
        sp.level5.filter(gid, 1000 + k, members, events)
        sp.write_pending()  # the world model's entity update
        sp.level5.groups = {gid: members}
        statuses.append(kd.get(gid).status)
    assert statuses[0] == Status.HYPOTHESIZED  # a group seen once is not confirmed
    assert Status.CONFIRMED in statuses
    first = statuses.index(Status.CONFIRMED)
    assert first + 1 >= tc.min_hits
    assert kd.get(gid).confidence > tc.confirm


def _segments(**over: float) -> SegmentAttributes:
    """One segment's attributes (a 5 m x 0.5 m x 2 m vertical plane of 200 returns), with
    ``over`` replacing some of them."""
    one = {
        "n_pixels": 200, "length_m": 5.0, "width_m": 0.5, "height_m": 2.0, "ground_z_m": 0.0,
        "clearance_m": 0.1, "area_m2": 2.5, "volume_m3": 5.0, "intensity": 0.4,
        "curvature": 0.001, "verticality": 0.02, "thickness_m": 0.01, "breadth_m": 0.6,
        "range_m": 10.0, "yaw_rad": 0.0, "t_offset_ns": 0,
    } | over  # fmt: skip
    arrays = {k: np.array([v]) for k, v in one.items()}
    xyz = np.array([[10.0, 0.0, 1.0]])
    return SegmentAttributes(centroid_xyz=xyz, center_xyz=xyz, **arrays)


def test_shape_is_averaged_over_sweeps_that_saw_a_surface_only() -> None:
    sp = KDSensoryProcessor(kd_store.open(":memory:"))
    sp.level4.observe_shape(7, _segments(), 0)
    first = sp.level4.shape_of(7)
    assert first["thickness_m"] == 0.01 and first["verticality"] == 0.02
    # one scan row of the same wall: a line, whose "normal" points anywhere
    sp.level4.observe_shape(7, _segments(breadth_m=0.01, verticality=0.97, length_m=9.0), 0)
    after = sp.level4.shape_of(7)
    assert after["verticality"] == 0.02  # the line said nothing of the surface
    assert after["longest_m"] == 9.0  # but more of the wall came into view
    assert 0.01 < after["breadth_m"] < 0.6
    assert sp.level4.shape_of(8) == {}  # never observed: the classifier leaves shape out


def _one_track(tid: int, what: tuple[float, float, float, float]):
    """The tracker's state of one confirmed track at rest at the origin with extents
    ``what`` (length, width, height m, yaw rad)."""
    from sp.tracking import Tracks, TrackStatus

    return Tracks(
        x=np.zeros((1, 6)),
        P=np.eye(6)[None] * 0.01,
        w=np.array([what], dtype=np.float64),
        Pw=np.full((1, 4), 0.01),
        t_ns=np.zeros(1, np.int64),
        id=np.array([tid], np.int64),
        status=np.array([TrackStatus.CONFIRMED], np.int8),
        confidence=np.ones(1),
        hits=np.full(1, 20, np.int64),
        misses=np.zeros(1, np.int64),
        nis=np.zeros(1),
        range_m=np.full(1, 20.0),
        xs=np.zeros((1, 3)),
        Ps=np.eye(3)[None] * 0.01,
        llr=np.full(1, -5.0),
        points=np.full(1, 200, np.int64),
    )


def test_a_class_taken_on_good_views_is_not_given_up_on_poor_ones() -> None:
    sp = KDSensoryProcessor(kd_store.open(":memory:"))
    level4, tid = sp.level4, 5
    wall, car_side = (9.0, 0.3, 1.5, 0.0), (4.2, 1.8, 1.5, 0.0)
    level4.tracker.tracks = _one_track(tid, wall)
    for t in range(6):  # passing it: 200 returns a sweep
        level4._seen_returns = {tid: 200}
        level4.classify(t)
    assert level4.track_class[tid][0] == "freestanding wall"
    # left behind, a few returns on a piece of it that has the extents of a car's side
    level4.tracker.tracks.w[0] = car_side
    for t in range(6, 10):
        level4._seen_returns = {tid: 12}
        level4.classify(t)
        assert level4.track_class[tid][0] == "freestanding wall", t
    # unmeasured (coasting), nothing changes either
    level4._seen_returns = {}
    level4.classify(10)
    assert level4.track_class[tid][0] == "freestanding wall"
    # a view as good as those the class rests on does change it
    level4._seen_returns = {tid: 150}
    level4.classify(11)
    assert level4.track_class[tid][0] == "vehicle"
    # with the rule off (share 0) the poor views alone would have
    sp0 = KDSensoryProcessor(kd_store.open(":memory:"), SPConfig(reclassify_min_share=0.0))
    sp0.level4.tracker.tracks = _one_track(tid, wall)
    sp0.level4._seen_returns = {tid: 200}
    sp0.level4.classify(0)
    sp0.level4.tracker.tracks.w[0] = car_side
    sp0.level4._seen_returns = {tid: 12}
    sp0.level4.classify(1)
    assert sp0.level4.track_class[tid][0] == "vehicle"


def test_class_evidence_lets_a_class_return_or_outlast_the_present_one() -> None:
    from sp.level4_objects import ClassEvidence

    ev = ClassEvidence()
    ev.take("rock", 80)
    for _ in range(5):
        ev.observe("rock", "rock", 90)
    assert not ev.may_change("rock", "vehicle", 30, 0.5)  # 30 < 0.5 x 90
    assert ev.may_change("rock", "vehicle", 45, 0.5)
    # taken as a vehicle on its nearest views (160 returns), the rock is seen as a rock again
    # from farther out: the rock was the track's class on a view as good as 0.5 x 160, a bush
    # never was
    ev.take("vehicle", 160)
    for _ in range(3):
        ev.observe("vehicle", "vehicle", 160)
    ev.observe("rock", "vehicle", 40)
    assert ev.may_change("vehicle", "rock", 40, 0.5)
    assert not ev.may_change("vehicle", "bush", 40, 0.5)
    # a tree near the sensor, its crown cut by the field of view, looks like a building on
    # the views with the most returns; from farther out it is a tree, in more views in a row
    # than it was ever a building
    tree = ClassEvidence()
    tree.take("building", 300)
    for _ in range(10):
        tree.observe("building", "building", 300)
    for k in range(11):
        tree.observe("tree", "building", 60)
        assert tree.may_change("building", "tree", 60, 0.5) == (k == 10), k
