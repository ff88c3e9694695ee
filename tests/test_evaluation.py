"""The scorer (wm.evaluation) on hand-built KDs and truths whose figures are known by
construction: MOTA, switches, precision, classification, static speed, don't-care, the body
frames of a moving, turning vehicle in an odometry world offset from the truth's, and the evo
trajectory figures."""

from __future__ import annotations

import math

import motmetrics as mm
import numpy as np
import pytest

import kd_store
from core.geometry import matrix_to_quat, rot_z, se3, transform_points
from kd_store import Level, State, Status
from logs.types import ObjectBoxes
from wm.evaluation import (
    EvalConfig,
    EvaluationError,
    Sweep,
    Truth,
    evaluate_run,
    load_kd,
    range_bands,
    trajectory_scores,
    unbounded_track,
)

DT = 100_000_000  # 10 Hz sweeps


def _box_set(t_ns: int, boxes: list[tuple]) -> ObjectBoxes:
    """World-frame truth boxes: each (id, class, (x, y), (l, w), yaw)."""
    return ObjectBoxes(
        t_ns, "world", np.array([b[0] for b in boxes], dtype=np.int64), [b[1] for b in boxes],
        np.array([[b[2][0], b[2][1], 1.0] for b in boxes]).reshape(-1, 3),
        np.array([[b[3][0], b[3][1], 2.0] for b in boxes]).reshape(-1, 3),
        np.array([b[4] for b in boxes], dtype=np.float64), np.zeros((len(boxes), 3)),
    )  # fmt: skip


def _truth(
    poses: list[np.ndarray],
    boxes: list[tuple],
    points_per_box: dict[int, int] | None = None,
    returns_on: dict[int, int] | None = None,
) -> Truth:
    """A truth of len(poses) sweeps at k * DT with the same static boxes at every time, and a
    sweep per time holding ``points_per_box[id]`` returns (default 10) at each box's centre
    (LADAR frame = body frame). ``returns_on``: the log's own count of each sweep's returns
    on each object (``ObjectBoxes.n_returns``), when it has one."""
    track = unbounded_track()
    sweeps, sets = [], []
    for k, T in enumerate(poses):
        t = k * DT
        track.add(t, T)
        sets.append(_box_set(t, boxes))
        if returns_on is not None:
            sets[-1].n_returns = np.array([returns_on.get(b[0], 0) for b in boxes])
        pts = [
            np.repeat([[b[2][0], b[2][1], 1.0]], (points_per_box or {}).get(b[0], 10), axis=0)
            for b in boxes
        ]
        p_world = np.vstack(pts) if pts else np.zeros((0, 3))
        p_body = transform_points(np.linalg.inv(T), p_world).astype(np.float32)
        sweeps.append(Sweep(t, p_body, np.zeros(len(p_body), dtype=np.int64)))
    return Truth.from_sweeps(track, sets, sweeps)


def _kd(
    self_poses: list[np.ndarray],
    tracks: dict[str, tuple[tuple[str, ...], dict[int, tuple]]],
    lag_ns: dict[str, int] | None = None,
) -> kd_store.KnowledgeDatabase:
    """A KD whose self entity has a state per pose (frame ``world``, at k * DT) and one object
    entity per track: name -> (generic classes, {frame k: ((x, y) odom, speed m/s)}), each
    state at k * DT plus the track's ``lag_ns`` (default 0: the object measured at the self
    time)."""
    kd = kd_store.open(":memory:")
    kd.begin_cycle(0)
    me = kd.add_entity("self", Level.OBJECT, generic_classes=("vehicle",))
    kd.update_entity(me.id, status=Status.CONFIRMED, confidence=1.0)
    ids = {}
    for name, (cls, _) in tracks.items():
        e = kd.add_entity(name, Level.OBJECT, generic_classes=cls)
        kd.update_entity(e.id, status=Status.CONFIRMED, confidence=0.9)
        ids[name] = e.id
    for k, T in enumerate(self_poses):
        t = k * DT
        kd.begin_cycle(t)
        kd.observe(me.id, State(t, "world", T[:3, 3], matrix_to_quat(T[:3, :3])))
        for name, (_, states) in tracks.items():
            if k in states:
                (x, y), v = states[k]
                t_obj = t + (lag_ns or {}).get(name, 0)
                kd.observe(
                    ids[name], State(t_obj, "world", (x, y, 1.0), velocity_xyz=(v, 0.0, 0.0))
                )
    kd.flush()
    return kd


def _score(truth: Truth, kd: kd_store.KnowledgeDatabase) -> dict:
    return evaluate_run(truth, load_kd(kd), EvalConfig())


STILL = [np.eye(4)] * 10


def test_mota_precision_classification_and_static_speed_by_construction():
    # vehicle found every frame (right class), person found as a vehicle (wrong class), tree
    # found from frame 5 on (right class), one false detection every frame
    boxes = [
        (1, "vehicle", (10.0, 0.0), (4.0, 2.0), 0.0),
        (2, "person", (0.0, 10.0), (0.6, 0.6), 0.0),
        (3, "tree", (20.0, 5.0), (1.0, 1.0), 0.0),
    ]
    tracks = {
        "a": (("vehicle",), {k: ((10.3, 0.2), 0.1) for k in range(10)}),
        "b": (("vehicle",), {k: ((0.0, 10.0), 0.3) for k in range(10)}),
        "d": (("vegetation", "tree"), {k: ((20.2, 5.0), 0.2) for k in range(5, 10)}),
        "fp": (("rock",), {k: ((-15.0, -15.0), 0.0) for k in range(10)}),
    }
    s = _score(_truth(STILL, boxes), _kd(STILL, tracks))
    assert s["num_objects"] == 30 and s["num_detections"] == 25
    assert s["num_misses"] == 5 and s["num_false_positives"] == 10 and s["num_switches"] == 0
    assert s["mota"] == pytest.approx(1 - (5 + 10) / 30)
    assert s["precision"] == pytest.approx(25 / 35)
    assert s["recall"] == pytest.approx(25 / 30)
    assert s["classification_accuracy"] == pytest.approx(15 / 25)
    # 10 pairs at 0.1, 5 at 0.2, 10 at 0.3 m/s: the median (13th of 25) is 0.2
    assert s["static_speed_median_mps"] == pytest.approx(0.2)
    assert s["static_speed_mean_mps"] == pytest.approx((10 * 0.1 + 5 * 0.2 + 10 * 0.3) / 25)
    assert s["persons_truth"] == 1 and s["persons_kd"] == 0 and s["person_count_error"] == 1
    assert s["motp"] == pytest.approx(0.0)  # every hypothesis inside its box's footprint
    assert s["hota"] < 1.0


def test_id_switch_counted_once_per_handover():
    boxes = [(1, "vehicle", (10.0, 0.0), (4.0, 2.0), 0.0)]
    tracks = {
        "a": (("vehicle",), {k: ((10.0, 0.0), 0.0) for k in range(5)}),
        "e": (("vehicle",), {k: ((10.5, 0.0), 0.0) for k in range(5, 10)}),
    }
    s = _score(_truth(STILL, boxes), _kd(STILL, tracks))
    # a's last state (frame 4) stays a hypothesis for 0.25 s: motmetrics keeps it matched up to
    # frame 6 (e is the false one at 5 and 6), the switch to e comes at frame 7
    assert s["num_switches"] == 1 and s["num_false_positives"] == 2
    assert s["mota"] == pytest.approx(1 - (2 + 1) / 10)
    assert s["switches_per_100"] == pytest.approx(10.0)
    assert s["precision"] == pytest.approx(10 / 12)
    assert s["idf1"] == pytest.approx(2 * 7 / (10 + 12))  # a holds the id for 7 frames


def test_the_states_of_the_scored_sweep_count_at_its_self_time():
    # the self pose is stamped at a sweep's middle, an object at its returns' own time, up to
    # half a sweep later: a state 30 ms after the self time is that sweep's, one 70 ms after
    # is the next sweep's (half of DT is 50 ms)
    boxes = [
        (1, "vehicle", (10.0, 0.0), (4.0, 2.0), 0.0),
        (2, "tree", (0.0, 12.0), (2.0, 2.0), 0.0),
    ]
    tracks = {
        "late_in_sweep": (("vehicle",), {k: ((10.0, 0.0), 0.0) for k in range(3, 10)}),
        "next_sweep": (("tree",), {k: ((0.0, 12.0), 0.0) for k in range(3, 10)}),
    }
    kd = _kd(STILL, tracks, {"late_in_sweep": 30_000_000, "next_sweep": 70_000_000})
    s = _score(_truth(STILL, boxes), kd)
    # the vehicle is found from frame 3 (its own sweep), the tree from frame 4
    assert s["num_objects"] == 20 and s["num_misses"] == 3 + 4
    assert s["num_false_positives"] == 0 and s["num_switches"] == 0
    assert s["recall_vehicle"] == pytest.approx(7 / 10)
    assert s["recall_tree"] == pytest.approx(6 / 10)


def test_dont_care_boxes_and_hypotheses_are_neither_tp_fp_nor_fn():
    boxes = [
        (4, "post", (40.6, 0.0), (0.4, 0.4), 0.0),  # footprint 40.4 m away: in the band
        (5, "rock", (0.0, -20.0), (1.0, 1.0), 0.0),  # 2 returns only: unseen
        (6, "wall", (30.0, 0.0), (1.0, 1.0), 0.0),  # seen, never detected: FN
        (7, "bush", (5.0, 5.0), (1.0, 1.0), 0.0),  # seen and detected: TP
    ]
    hyp = {
        "on_band_box": (4, (40.6, 0.0)),
        "on_unseen_box": (5, (0.0, -20.0)),
        "band_alone": (0, (-40.6, 0.0)),  # in the band, matches nothing: not FP
        "bush": (7, (5.0, 5.0)),
        "far_alone": (0, (0.0, 39.5)),  # inside range, matches nothing: FP
    }
    tracks = {n: (("post",), {k: (xy, 0.0) for k in range(10)}) for n, (_, xy) in hyp.items()}
    s = _score(_truth(STILL, boxes, {5: 2}), _kd(STILL, tracks))
    assert s["num_objects"] == 20  # boxes 6 and 7 at each of 10 times
    assert s["num_detections"] == 10 and s["num_misses"] == 10
    assert s["num_false_positives"] == 10  # far_alone only
    assert s["mota"] == pytest.approx(1 - 20 / 20)
    assert s["precision"] == pytest.approx(0.5)


def test_a_pair_is_in_range_when_its_box_is():
    # a 20 m deep building whose near face is 35 m away: the entity at its centre (45 m) is
    # the building found (TP); an entity 45 m away on nothing takes no part
    boxes = [(8, "building", (45.0, 0.0), (20.0, 12.0), 0.0)]
    tracks = {
        "building": (("building",), {k: ((45.0, 0.0), 0.0) for k in range(10)}),
        "beyond": (("rock",), {k: ((0.0, 45.0), 0.0) for k in range(10)}),
    }
    s = _score(_truth(STILL, boxes, {8: 50}), _kd(STILL, tracks))
    assert s["num_objects"] == 10 and s["num_detections"] == 10
    assert s["num_false_positives"] == 0 and s["mota"] == pytest.approx(1.0)


def test_recall_by_band_of_box_range_by_construction():
    # a rock 10 m out found every frame, one 25 m out from the sixth on, a wall whose near face
    # is 34.5 m out (centre 35 m) never; the bands are [0, 20), [20, 30), [30, 40] m
    boxes = [
        (1, "rock", (10.0, 0.0), (1.0, 1.0), 0.0),
        (2, "rock", (0.0, 25.0), (1.0, 1.0), 0.0),
        (3, "wall", (-35.0, 0.0), (1.0, 1.0), 0.0),
    ]
    tracks = {
        "near": (("rock",), {k: ((10.0, 0.0), 0.0) for k in range(10)}),
        "mid": (("rock",), {k: ((0.0, 25.0), 0.0) for k in range(5, 10)}),
    }
    s = _score(_truth(STILL, boxes), _kd(STILL, tracks))
    assert s["box_frames_0_20m"] == 10 and s["recall_0_20m"] == pytest.approx(1.0)
    assert s["box_frames_20_30m"] == 10 and s["recall_20_30m"] == pytest.approx(0.5)
    assert s["box_frames_30_40m"] == 10 and s["recall_30_40m"] == pytest.approx(0.0)
    # by class the same box-frames: the rocks 15 of 20, the wall none
    assert s["recall_rock"] == pytest.approx(0.75) and s["recall_wall"] == 0.0
    # the bands partition the scored box-frames: their hits are the run's detections
    hits = sum(s[f"recall_{b}"] * s[f"box_frames_{b}"] for b in ("0_20m", "20_30m", "30_40m"))
    assert hits == pytest.approx(s["num_detections"])


def test_recall_at_the_start_and_after_by_construction():
    # 2 s of 10 Hz sweeps; a rock found from the fourth sweep on (its track confirmed late, as
    # at a log's start), a post with states up to sweep 12, which the 0.25 s state window
    # holds through sweep 14: found in every sweep but the last five
    boxes = [(1, "rock", (10.0, 0.0), (1.0, 1.0), 0.0), (2, "post", (0.0, 15.0), (0.3, 0.3), 0.0)]
    tracks = {
        "rock": (("rock",), {k: ((10.0, 0.0), 0.0) for k in range(3, 20)}),
        "post": (("post",), {k: ((0.0, 15.0), 0.0) for k in range(13)}),
    }
    still = [np.eye(4)] * 20
    s = _score(_truth(still, boxes), _kd(still, tracks))
    assert s["box_frames_startup"] == 20 and s["recall_startup"] == pytest.approx(17 / 20)
    assert s["box_frames_steady"] == 20 and s["recall_steady"] == pytest.approx(15 / 20)
    hits = s["recall_startup"] * 20 + s["recall_steady"] * 20
    assert hits == pytest.approx(s["num_detections"])
    with pytest.raises(EvaluationError, match="startup_s -1"):
        evaluate_run(_truth(still, boxes), load_kd(_kd(still, tracks)), EvalConfig(startup_s=-1))


def test_range_bands_that_do_not_rise_within_the_range_are_refused():
    with pytest.raises(EvaluationError, match=r"range_bands_m \(30.0, 20.0\)"):
        range_bands(EvalConfig(range_bands_m=(30.0, 20.0)))
    with pytest.raises(EvaluationError, match="range_bands_m"):
        range_bands(EvalConfig(range_bands_m=(20.0, 45.0)))  # past the 40 m range
    assert range_bands(EvalConfig()) == [(0.0, 20.0), (20.0, 30.0), (30.0, 40.0)]


def _circle_poses(n: int) -> list[np.ndarray]:
    """A vehicle driving a 30 m radius circle at 8 m/s, heading along it (body x forward)."""
    out = []
    for k in range(n):
        a = k * DT * 1e-9 * 8.0 / 30.0
        out.append(se3(rot_z(a + math.pi / 2), np.array([30 * math.cos(a), 30 * math.sin(a), 0])))
    return out


def test_body_frames_of_a_turning_vehicle_in_an_offset_odometry_world():
    poses = _circle_poses(20)
    G = se3(rot_z(0.7), np.array([100.0, -50.0, 2.0]))  # odometry world vs truth world
    est = [G @ T for T in poses]
    boxes = [(1, "vehicle", (0.0, 0.0), (4.0, 2.0), 0.3), (2, "tree", (35.0, 10.0), (1, 1), 0.0)]
    tracks = {
        name: (("vehicle",) if i == 1 else ("tree",), {k: (tuple(p[:2]), 0.0) for k in range(20)})
        for name, i, p in [
            ("v", 1, transform_points(G, np.array([[0.0, 0.0, 1.0]]))[0]),
            ("t", 2, transform_points(G, np.array([[35.0, 10.0, 1.0]]))[0]),
        ]
    }
    s = _score(_truth(poses, boxes), _kd(est, tracks))
    assert s["num_objects"] == 40
    assert s["mota"] == pytest.approx(1.0) and s["precision"] == pytest.approx(1.0)
    assert s["classification_accuracy"] == pytest.approx(1.0)
    assert s["ape_rmse_m"] == pytest.approx(0.0, abs=1e-6)  # G is rigid: Umeyama removes it
    assert s["drift_pct"] == pytest.approx(0.0, abs=1e-6)  # align_origin removes it too


def test_hypotheses_in_the_truth_world_instead_of_the_odometry_world_are_not_matched():
    poses = _circle_poses(10)
    G = se3(rot_z(0.7), np.array([100.0, -50.0, 2.0]))
    boxes = [(1, "vehicle", (0.0, 0.0), (4.0, 2.0), 0.3)]
    tracks = {"v": (("vehicle",), {k: ((0.0, 0.0), 0.0) for k in range(10)})}  # not moved by G
    s = _score(_truth(poses, boxes), _kd([G @ T for T in poses], tracks))
    assert s["num_detections"] == 0 and s["mota"] == pytest.approx(0.0)


def test_mota_and_idf1_equal_a_direct_motmetrics_computation():
    boxes = [(1, "vehicle", (10.0, 0.0), (4.0, 2.0), 0.0), (2, "post", (0.0, 12.0), (1, 1), 0.0)]
    tracks = {
        "a": (("vehicle",), {k: ((10.5, 0.0), 0.0) for k in range(6)}),
        "b": (("vehicle",), {k: ((11.0, 0.0), 0.0) for k in range(6, 10)}),
        "c": (("post",), {k: ((0.0, 13.4), 0.0) for k in range(0, 10, 2)}),  # 0.9 m off
    }
    s = _score(_truth(STILL, boxes), _kd(STILL, tracks))
    assert s["num_switches"] == 1  # a hands over to b once a's window has passed
    acc = mm.MOTAccumulator(auto_id=True)
    for k in range(10):
        # a hypothesis at k: a state at k, k-1 or k-2 (the 0.25 s window at 10 Hz)
        hids, row1, row2 = [], [], []
        for hid, name in ((1, "a"), (2, "b"), (3, "c")):
            if {k, k - 1, k - 2} & set(tracks[name][1]):
                hids.append(hid)
                row1.append(np.nan if hid == 3 else 0.0)  # a and b inside the vehicle's box
                row2.append(0.9 if hid == 3 else np.nan)  # c 0.9 m from the post's footprint
        acc.update([1, 2], hids, np.array([row1, row2]).reshape(2, len(hids)))
    ref = mm.metrics.create().compute(acc, metrics=["mota", "idf1", "motp"], name="x").iloc[0]
    assert s["mota"] == pytest.approx(ref["mota"])
    assert s["idf1"] == pytest.approx(ref["idf1"])
    assert s["motp"] == pytest.approx(ref["motp"], abs=1e-9)


def test_evo_constant_offset_and_known_drift():
    t = np.arange(101) * DT
    # an L-shaped 100 m path (50 m along x, then 50 m along y), heading kept
    xy = [(float(min(k, 50)), float(max(k - 50, 0))) for k in range(101)]
    true = [se3(np.eye(3), np.array([x, y, 0.0])) for x, y in xy]
    # a constant offset of (5, 5, 0) m plus a vertical drift of 1 % of the distance driven
    est = [se3(np.eye(3), np.array([x + 5.0, y + 5.0, 0.01 * k])) for k, (x, y) in enumerate(xy)]
    s = trajectory_scores(t, np.stack(est), np.stack(true))
    assert s["path_m"] == pytest.approx(100.0)
    assert s["final_error_m"] == pytest.approx(1.0, abs=1e-9)
    assert s["drift_pct"] == pytest.approx(1.0, abs=1e-7)
    assert s["rpe_pct"] == pytest.approx(1.0, abs=1e-6)  # 0.1 m over every 10 m segment
    assert 0.0 < s["ape_rmse_m"] < 0.5  # Umeyama spreads the drift: less than its 1 m end
    offset_only = [se3(np.eye(3), T[:3, 3] + [5.0, 5.0, 0.0]) for T in true]
    s0 = trajectory_scores(t, np.stack(offset_only), np.stack(true))
    assert s0["ape_rmse_m"] == pytest.approx(0.0, abs=1e-9)
    assert s0["drift_pct"] == pytest.approx(0.0, abs=1e-9)
    assert s0["rpe_pct"] == pytest.approx(0.0, abs=1e-9)


def test_a_kd_without_self_is_refused():
    from wm.evaluation import EvaluationError

    kd = kd_store.open(":memory:")
    kd.begin_cycle(0)
    kd.add_entity("tree", Level.OBJECT, status=Status.CONFIRMED, confidence=0.9)
    with pytest.raises(EvaluationError, match="self"):
        load_kd(kd)


def test_claimed_classes_go_up_the_library_never_down() -> None:
    from wm.evaluation import predicted_classes

    is_a = {"freestanding wall": "wall", "wall": "surface", "tree": "vegetation"}
    assert predicted_classes(["object", "freestanding wall"], None, is_a) == {
        "freestanding wall", "wall", "surface",
    }  # fmt: skip
    assert "tree" not in predicted_classes(["object", "vegetation"], None, is_a)
    assert predicted_classes(None, "tree", is_a) == {"tree", "vegetation"}
    assert predicted_classes(["REGULAR_VEHICLE"], None, {}) == {"vehicle"}


def test_seen_is_the_returns_on_the_object_when_the_log_counts_them():
    # box 6 has 10 returns in its box, all on something else (the ground under a car seen
    # through a gap): the log's count of returns on it says 0, so it is not scored; box 7 has
    # none in its box but the log counts 10 on it, so it is scored (and missed)
    boxes = [
        (6, "vehicle", (10.0, 0.0), (4.0, 2.0), 0.0),
        (7, "vehicle", (20.0, 5.0), (4.0, 2.0), 0.0),
    ]
    in_box = {6: 10, 7: 0}
    s = _score(_truth(STILL, boxes, in_box, returns_on={7: 10}), _kd(STILL, {}))
    assert s["num_objects"] == 10 and s["num_misses"] == 10
    assert _truth(STILL, boxes, in_box, returns_on={7: 10}).seen[0].count(
        np.array([6, 7])
    ).tolist() == [0, 10]
    # without the log's count: the returns in the grown box
    assert _truth(STILL, boxes, in_box).seen[0].count(np.array([6, 7])).tolist() == [10, 0]
