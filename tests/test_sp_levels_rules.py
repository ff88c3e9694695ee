"""Unit tests of the second round of SP levels 2-5 rules, each against analytic truth:
deskewing, ground continuity along the column's slope, terrain patches, line continuity,
cascade association, parts and duplicates, partial views, evident speed, M-of-N birth, camera
appearance."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import kd_store
from logs.types import CameraFrame, LadarScan
from sp.appearance import object_appearance
from sp.computation import ground_below, segment_attributes
from sp.egosphere import EgosphereConfig
from sp.level3_surfaces import terrain_patch
from sp.level4_objects import largest_segment_of_track
from sp.pipeline import SPConfig
from sp.segments import merge_collinear
from sp.tracking import (
    Measurements,
    Tracker,
    TrackerConfig,
    TrackStatus,
    associate,
    evident_speed,
    measurement_R,
)
from wm.entities import KDSensoryProcessor

SWEEP_NS = 100_000_000


def _wall_world(x_m: float = 20.0) -> np.ndarray:
    """(N, 3) world points of a wall facing the sensor: x = x_m, |y| <= 8, 0 <= z <= 3."""
    y, z = np.meshgrid(np.linspace(-8.0, 8.0, 161), np.linspace(0.0, 3.0, 16))
    return np.stack([np.full(y.size, x_m), y.ravel(), z.ravel()], axis=1)


def _moving_sweep(p_world: np.ndarray, t_ns: int, v_mps: float) -> LadarScan:
    """A sweep of ``p_world`` by a sensor moving along +x at ``v_mps`` (at x = v t, z = 1.8),
    each point measured at its own firing time (azimuth order over one 100 ms sweep)."""
    az = np.arctan2(p_world[:, 1] - 0.0, p_world[:, 0] - v_mps * t_ns * 1e-9)
    off = np.round((np.pi - az) / (2 * np.pi) * SWEEP_NS).astype(np.int64)
    sensor = np.stack([v_mps * (t_ns + off) * 1e-9, np.zeros(off.size), np.full(off.size, 1.8)], 1)
    pts = (p_world - sensor).astype(np.float32)
    return LadarScan(t_ns, "ladar", pts, np.ones(len(pts), np.float32), off)


def _pose(t_ns: int, v_mps: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3], T[2, 3] = v_mps * t_ns * 1e-9, 1.8
    return T


def test_deskew_puts_a_static_wall_back_in_place() -> None:
    p_world = _wall_world()
    v = 10.0
    cfg = SPConfig(egosphere=EgosphereConfig(n_rows=64, n_cols=1024, max_returns=1))
    sp = KDSensoryProcessor(kd_store.open(":memory:"), cfg)
    errors = []
    for k in range(2):
        t = k * SWEEP_NS
        r = sp.process(_moving_sweep(p_world, t, v), _pose(t, v))
        e = np.linalg.norm(r.points_world - p_world[r.point_index], axis=1)
        errors.append(float(e.max()))
    # first sweep: one pose for the whole sweep, points off by up to v * (time after stamp)
    assert errors[0] > 0.3
    # second: each column at its own pose (constant velocity between the two sweep poses)
    assert errors[1] < 0.01


def test_ground_below_continues_the_column_slope() -> None:
    # one column, rows bottom-up at ranges 4, 5, 6 m on a 10 % slope, then an object at 10 m
    r = np.array([[10.0], [6.0], [5.0], [4.0]])
    z = 0.1 * r
    ground = np.array([[False], [True], [True], [True]])
    nearest = ground_below(ground, z)
    sloped = ground_below(ground, z, r)
    assert nearest[0, 0] == pytest.approx(0.6)
    assert sloped[0, 0] == pytest.approx(1.0)  # the hillside under the object's pixel


def _attrs_of(points: np.ndarray, ground_z: float = 0.0):
    n = points.shape[0]
    labels = np.zeros((1, n), np.int64)
    return segment_attributes(
        labels,
        points.reshape(1, n, 3),
        np.ones((1, n)),
        np.full((1, n), 10.0),
        np.zeros((1, n), np.int64),
        np.full((1, n), ground_z),
    )


def test_terrain_patch_is_a_low_gentle_plane_not_a_wall_or_roof() -> None:
    u, v = np.meshgrid(np.linspace(0, 3, 12), np.linspace(0, 2, 8))
    u, v = u.ravel(), v.ravel()
    cfg = SPConfig()
    hill = np.stack([u, v, 0.3 * u], axis=1)  # 17 degrees, rises 0.9 m
    wall = np.stack([u, np.zeros_like(u), v], axis=1)
    roof = np.stack([u, v, np.full_like(u, 4.0)], axis=1)
    flags = [bool(terrain_patch(_attrs_of(p), cfg)[0]) for p in (hill, wall, roof)]
    assert flags == [True, False, False]


def test_a_bank_as_steep_as_loose_soil_stands_is_terrain_a_steeper_face_is_not() -> None:
    u, v = np.meshgrid(np.linspace(0, 1.2, 8), np.linspace(0, 2, 8))
    u, v = u.ravel(), v.ravel()
    cfg = SPConfig()
    bank = np.stack([u, v, np.tan(np.radians(40.0)) * u], axis=1)  # a ditch's side, 1 m high
    face = np.stack([0.65 * u, v, np.tan(np.radians(55.0)) * 0.65 * u], axis=1)  # as high
    flags = [bool(terrain_patch(_attrs_of(p), cfg)[0]) for p in (bank, face)]
    assert flags == [True, False]


def test_line_continuity_joins_pieces_of_a_wall_not_a_row_of_cars() -> None:
    # a wall along x cut into three pieces with 1 m gaps, a post 3 m off its line
    centers = np.array([[0.0, 0.0], [6.0, 0.0], [11.0, 0.0], [6.0, 3.0]])
    length = np.array([5.0, 5.0, 3.0, 0.3])
    width = np.array([0.3, 0.3, 0.3, 0.3])
    yaw = np.zeros(4)
    lab = merge_collinear(centers, yaw, length, width, np.full(4, 20.0))
    assert lab[0] == lab[1] == lab[2] and lab[3] != lab[0]
    # two cars nose to tail 7.5 m apart stay two
    lab = merge_collinear(
        np.array([[0.0, 0.0], [12.0, 0.0]]),
        np.zeros(2),
        np.array([4.5, 4.5]),
        np.array([1.2, 1.2]),
        np.full(2, 20.0),
    )
    assert lab[0] != lab[1]


def test_confirmed_tracks_are_assigned_before_hypotheses() -> None:
    cfg = TrackerConfig()
    x = np.zeros((2, 6))
    x[0, 0], x[1, 0] = 0.0, 1.0  # the measurement at 0.6 m is nearer the hypothesis ...
    P = np.stack([np.eye(6) * 0.05, np.eye(6) * 25.0])  # ... whose covariance is wide
    meas = Measurements(np.array([[0.6, 0.0, 0.0]]), np.zeros(1, np.int64), np.ones((1, 4)))
    ti, mi = associate(x, P, meas, cfg)
    assert ti.tolist() == [1]  # one stage: the wide hypothesis is the cheapest
    ti, mi = associate(x, P, meas, cfg, np.array([True, False]))
    assert ti.tolist() == [0] and mi.tolist() == [0]


def _what(length: float, width: float = 0.4, yaw: float = 0.0) -> np.ndarray:
    return np.array([[length, width, 2.0, yaw]])


def test_piece_inside_a_footprint_is_a_part_and_a_duplicate_goes() -> None:
    tr = Tracker()
    for k in range(5):  # a confirmed 10 m wall at the origin
        t = k * SWEEP_NS
        tr.step(Measurements(np.zeros((1, 3)), np.array([t]), _what(10.0)), t)
    assert tr.tracks.status[0] == TrackStatus.CONFIRMED
    t = 5 * SWEEP_NS
    pieces = Measurements(
        np.array([[0.0, 0.0, 0.0], [4.0, 0.2, 0.0]]), np.array([t, t]), np.vstack([_what(10.0)] * 2)
    )
    track_of, _ = tr.step(pieces, t)
    assert len(tr.tracks) == 1 and track_of.tolist() == [0, 0]


def test_a_tracks_largest_segment_speaks_for_it_not_a_sliver_that_joined_it() -> None:
    # segments 0 (a car's side, 500 returns) and 2 (a sliver of its far edge, 6) went to
    # track 1; segment 1 to track 0; segment 3 to none
    track_of = np.array([1, 0, 1, -1])
    n_pixels = np.array([500, 40, 6, 90])
    assert largest_segment_of_track(track_of, n_pixels, 3).tolist() == [1, 0, -1]
    # in the other order, the same answer: the sliver never speaks for the car
    assert largest_segment_of_track(track_of[[2, 1, 0, 3]], n_pixels[[2, 1, 0, 3]], 3).tolist() == [
        1,
        2,
        -1,
    ]
    # three pieces of one track, two of them as large: the later of those; none at all: -1
    assert largest_segment_of_track(np.array([0, 0, 0]), np.array([7, 9, 9]), 1).tolist() == [2]
    assert largest_segment_of_track(np.zeros(0, np.int64), np.zeros(0), 2).tolist() == [-1, -1]


def _status_after_hits(
    n_points: int | None, hits: int, neighbour_at_m: float | None = 1.0, height_m: float = 2.0
) -> TrackStatus:
    """The status of a 0.6 x 0.5 m track ``height_m`` tall at the origin after ``hits``
    sweeps, with a 4 x 2 m body of 500 returns (a car) seen beside it, its near side
    ``neighbour_at_m`` m away (None: nothing else in view)."""
    tr = Tracker()
    for k in range(hits):
        t = k * SWEEP_NS
        pos, what = np.zeros((1, 3)), _what(0.6, 0.5)
        what[0, 2] = height_m
        pts = None if n_points is None else np.array([n_points])
        if neighbour_at_m is not None:
            y = 0.25 + neighbour_at_m + 1.0  # the car's centre: its 2 m width across y
            pos = np.array([[0.0, 0.0, 0.0], [0.0, y, 0.0]])
            what = np.vstack([what, _what(4.0, 2.0)])
            pts = None if pts is None else np.array([n_points, 500])
        tr.step(Measurements(pos, np.full(len(pos), t), what, None, pts), t)
    k = int(np.argmin(np.linalg.norm(tr.tracks.x[:, :2], axis=1)))
    return TrackStatus(int(tr.tracks.status[k]))


def test_a_few_returns_need_more_sweeps_to_be_confirmed() -> None:
    cfg = TrackerConfig()
    assert cfg.min_hits_alone < cfg.min_hits_small
    # a few returns beside a larger object: more often a piece of it than an object of its
    # own, so still a hypothesis when a large object would be confirmed
    assert _status_after_hits(cfg.small_points, cfg.min_hits) == TrackStatus.HYPOTHESIZED
    assert _status_after_hits(cfg.small_points, cfg.min_hits_small) == TrackStatus.CONFIRMED
    assert _status_after_hits(cfg.small_points + 1, cfg.min_hits) == TrackStatus.CONFIRMED
    # measurements that do not say how many returns they hold are taken as objects
    assert _status_after_hits(None, cfg.min_hits) == TrackStatus.CONFIRMED


@pytest.mark.parametrize("neighbour_at_m", [None, 4.5, 10.0])
def test_a_few_returns_alone_are_confirmed_sooner(neighbour_at_m: float | None) -> None:
    # a rock far out in a field: nothing within alone_m, so it is confirmed at
    # min_hits_alone, where beside a car (the test above, 1 m) it needs min_hits_small
    cfg = TrackerConfig()
    assert neighbour_at_m is None or neighbour_at_m > cfg.alone_m
    assert cfg.min_hits_alone < cfg.min_hits_small
    before = _status_after_hits(cfg.small_points, cfg.min_hits_alone - 1, neighbour_at_m)
    assert before == TrackStatus.HYPOTHESIZED
    after = _status_after_hits(cfg.small_points, cfg.min_hits_alone, neighbour_at_m)
    assert after == TrackStatus.CONFIRMED


def test_a_flat_fold_or_a_sparse_one_alone_waits_for_the_extra_hit() -> None:
    # a few centimetres of terrain along one scan row far out in a field: nothing beside it,
    # but no taller than a fold of the ground, so it needs min_hits_small like clutter
    cfg = TrackerConfig()
    fold = _status_after_hits(cfg.small_points, cfg.min_hits_alone, None, height_m=0.08)
    assert fold == TrackStatus.HYPOTHESIZED
    assert _status_after_hits(cfg.small_points, cfg.min_hits_small, None, height_m=0.08) == (
        TrackStatus.CONFIRMED
    )
    # ... and so does a thin upright thing of too few returns to be named by
    sparse = _status_after_hits(cfg.alone_min_points - 1, cfg.min_hits_alone, None)
    assert sparse == TrackStatus.HYPOTHESIZED
    assert _status_after_hits(cfg.alone_min_points, cfg.min_hits_alone, None) == (
        TrackStatus.CONFIRMED
    )
    low_rock = cfg.alone_min_height_m + 0.05
    rock = _status_after_hits(cfg.small_points, cfg.min_hits_alone, None, height_m=low_rock)
    assert rock == TrackStatus.CONFIRMED


@pytest.mark.parametrize("neighbour_at_m", [1.0, 2.0, 3.5])
def test_a_few_returns_beside_a_body_wait_for_the_extra_hit(neighbour_at_m: float) -> None:
    cfg = TrackerConfig()
    assert neighbour_at_m < cfg.alone_m
    held = _status_after_hits(cfg.small_points, cfg.min_hits_alone, neighbour_at_m)
    assert held == TrackStatus.HYPOTHESIZED
    assert _status_after_hits(cfg.small_points, cfg.min_hits_small, neighbour_at_m) == (
        TrackStatus.CONFIRMED
    )


def test_a_track_once_seen_large_is_not_held_back_by_a_partial_view() -> None:
    tr = Tracker()
    for k, n in enumerate([200, 4, 4]):  # a car, then only a corner of it in view
        t = k * SWEEP_NS
        tr.step(Measurements(np.zeros((1, 3)), np.array([t]), _what(4.5), None, np.array([n])), t)
    assert tr.tracks.points[0] == 200 and tr.tracks.status[0] == TrackStatus.CONFIRMED


def test_a_young_track_on_a_confirmed_footprint_is_a_piece_of_it() -> None:
    # a building face confirmed; a sliver of its side, seen edge-on, started its own track
    # beyond the part margin, then the face's footprint grew over it
    tr = Tracker()
    for k in range(5):
        t = k * SWEEP_NS
        tr.step(Measurements(np.zeros((1, 3)), np.array([t]), _what(6.0)), t)
    t = 5 * SWEEP_NS
    both = Measurements(
        np.array([[0.0, 0.0, 0.0], [4.2, 0.0, 0.0]]), np.array([t, t]),
        np.vstack([_what(6.0), _what(0.6, 0.05)]),
    )  # fmt: skip
    track_of, _ = tr.step(both, t)
    assert len(tr.tracks) == 2 and track_of.tolist() == [0, 1]  # beyond the margin: its own
    young = tr.tracks.hits[1]
    for k in range(6, 9):  # the face is now seen 10 m long; the sliver lies on it
        t = k * SWEEP_NS
        both = Measurements(
            np.array([[2.0, 0.0, 0.0], [4.2, 0.0, 0.0]]), np.array([t, t]),
            np.vstack([_what(10.0), _what(0.6, 0.05)]),
        )  # fmt: skip
        track_of, _ = tr.step(both, t)
        assert track_of.tolist() == [0, 0]  # the sliver's measurement goes to the face
    assert tr.tracks.status[0] == TrackStatus.CONFIRMED
    # the sliver's own track got no more hits and was denied
    assert tr.tracks.hits[1] == young and tr.tracks.status[1] == TrackStatus.DENIED


def test_a_small_object_beside_a_confirmed_one_keeps_its_track() -> None:
    # a person 2 m from a parked car's side: outside its footprint and margin
    tr = Tracker()
    for k in range(6):
        t = k * SWEEP_NS
        both = Measurements(
            np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]]), np.array([t, t]),
            np.vstack([_what(4.5, 1.8), _what(0.5, 0.5)]),
        )  # fmt: skip
        track_of, _ = tr.step(both, t)
    assert track_of.tolist() == [0, 1]
    assert (tr.tracks.status == TrackStatus.CONFIRMED).all()


def _parked(tr: Tracker, xy: list[tuple[float, float]], what: list, points: list[int], k0: int):
    """Sweeps k0..k0+7 of static pieces at ``xy`` (world m) with extents ``what`` (each
    (1, 4)) and ``points`` returns; returns the last sweep's track of each measurement."""
    for k in range(k0, k0 + 8):
        t = k * SWEEP_NS
        meas = Measurements(
            np.array([[x, y, 0.0] for x, y in xy]), np.full(len(xy), t), np.vstack(what),
            None, np.array(points),
        )  # fmt: skip
        track_of, _ = tr.step(meas, t)
    return track_of


def test_two_pieces_of_a_parked_vehicle_become_one_track() -> None:
    # a car's end (1.8 m across, 40 returns) and its side beyond the car parked beside it
    # (1.5 m long, 120 returns), 1.3 m apart: two confirmed tracks at rest
    tr = Tracker()
    xy, what = [(0.0, 0.0), (1.2, 0.5)], [_what(1.8, 0.3, math.pi / 2), _what(1.5, 0.3)]
    assert _parked(tr, xy, what, [40, 120], 0).tolist() == [0, 1]
    assert (tr.tracks.status == TrackStatus.CONFIRMED).all()
    ended = tr.merge_pieces(np.array([True, True]), 1.5)
    # the piece of fewer returns ends; the other's footprint holds both: x -0.15..1.95 (the
    # end's thickness to the side's far end), y -0.9..0.9 (the end's breadth)
    assert ended.tolist() == [0]
    assert tr.tracks.status.tolist() == [TrackStatus.GONE, TrackStatus.CONFIRMED]
    np.testing.assert_allclose(tr.tracks.w[1, :2], [2.1, 1.8], atol=0.02)
    np.testing.assert_allclose(tr.tracks.x[1, :2], [0.9, 0.0], atol=0.02)
    np.testing.assert_allclose(tr.tracks.xs[1, :2], [0.9, 0.0], atol=0.02)
    tr.drop_finished()
    # from then on both pieces are measurements of the one track
    assert _parked(tr, xy, what, [40, 120], 8).tolist() == [0, 0] and len(tr.tracks) == 1


def test_vehicles_a_body_apart_moving_or_of_another_class_keep_their_tracks() -> None:
    two = [_what(4.5, 1.8), _what(4.5, 1.8)]
    tr = Tracker()
    _parked(tr, [(0.0, 0.0), (0.0, 2.4)], two, [300, 300], 0)  # side by side, 2.4 m apart
    assert tr.merge_pieces(np.array([True, True]), 1.5).size == 0
    tr = Tracker()
    _parked(tr, [(0.0, 0.0), (1.2, 0.5)], two, [300, 300], 0)
    assert tr.merge_pieces(np.array([True, False]), 1.5).size == 0  # a person by a car
    tr.tracks.llr[1] = TrackerConfig().llr_max  # one of them driving
    assert tr.merge_pieces(np.array([True, True]), 1.5).size == 0
    assert (tr.tracks.status == TrackStatus.CONFIRMED).all()


def test_a_buildings_front_and_side_meeting_at_its_corner_become_one_track() -> None:
    # the front (10 m, 300 returns) along x, the side seen at a grazing angle (6 m, 100
    # returns) along y from the front's right end: their centres 5.9 m apart, their
    # footprints meeting at the corner
    tr = Tracker()
    xy = [(0.0, 0.0), (5.1, 3.1)]
    what = [_what(10.0, 0.3), _what(6.0, 0.3, math.pi / 2)]
    assert _parked(tr, xy, what, [300, 100], 0).tolist() == [0, 1]
    assert tr.merge_pieces(np.array([True, True]), 1.5).size == 0  # centres too far apart
    ended = tr.merge_touching(np.array([True, True]), 0.5)
    assert ended.tolist() == [1]
    assert tr.tracks.status.tolist() == [TrackStatus.CONFIRMED, TrackStatus.GONE]
    # the front's footprint grows over the side: x -5..5.25, y -0.15..6.1
    np.testing.assert_allclose(tr.tracks.w[0, :2], [10.25, 6.25], atol=0.05)
    np.testing.assert_allclose(tr.tracks.x[0, :2], [0.125, 2.975], atol=0.05)
    tr.drop_finished()
    assert _parked(tr, xy, what, [300, 100], 8).tolist() == [0, 0] and len(tr.tracks) == 1


def test_buildings_apart_of_another_class_or_moving_keep_their_tracks() -> None:
    # two fronts in a row with a 1.5 m passage between them
    fronts = [_what(10.0, 0.3), _what(10.0, 0.3)]
    tr = Tracker()
    _parked(tr, [(0.0, 0.0), (11.5, 0.0)], fronts, [300, 300], 0)
    assert tr._footprint_gaps(np.array([0, 1]))[0, 1] == pytest.approx(1.5, abs=0.05)
    assert tr.merge_touching(np.array([True, True]), 0.5).size == 0
    # ... and touching, but one of them not a building, or driving
    tr = Tracker()
    _parked(tr, [(0.0, 0.0), (10.2, 0.0)], fronts, [300, 300], 0)
    assert tr.merge_touching(np.array([True, False]), 0.5).size == 0
    tr.tracks.llr[1] = TrackerConfig().llr_max
    assert tr.merge_touching(np.array([True, True]), 0.5).size == 0
    assert (tr.tracks.status == TrackStatus.CONFIRMED).all()


def test_the_tracks_of_a_class_include_its_kinds_and_a_missing_class_has_none() -> None:
    sp = KDSensoryProcessor(kd_store.open(":memory:"))
    l4 = sp.level4
    ids = [101, 102, 103, 104]
    l4.tracker.tracks = l4.tracker.tracks.extend(
        l4.tracker._births(
            Measurements(np.zeros((4, 3)), np.zeros(4, np.int64), np.vstack([_what(4.0)] * 4)),
            np.arange(4),
            np.array(ids),
        )
    )
    # a specific class founded under vehicle (as a confirmed object matching no class founds one)
    sp.ctx.classes.add(
        dataclasses.replace(sp.ctx.classes.get("vehicle"), name="van", is_a="vehicle")
    )
    l4.track_class.update({101: ("vehicle", 0.9), 102: ("van", 0.8), 103: ("person", 0.9)})
    assert l4._of_class("vehicle").tolist() == [True, True, False, False]
    assert l4._of_class("no such class").tolist() == [False] * 4


def test_a_building_lost_while_its_filter_drifted_is_remembered_at_rest() -> None:
    # two tracks gone unseen, both filters at 2 m/s and found moving: a building (a face
    # sliding into view can do that to its filter) and a vehicle
    sp = KDSensoryProcessor(kd_store.open(":memory:"))
    l4 = sp.level4
    tracks = l4.tracker._births(
        Measurements(np.zeros((2, 3)), np.zeros(2, np.int64), np.vstack([_what(4.0)] * 2)),
        np.arange(2),
        np.array([201, 202]),
    )
    tracks.x[:, 3] = 2.0
    tracks.llr[:] = TrackerConfig().llr_max
    tracks.status[:] = TrackStatus.GONE
    tracks.misses[:] = 9
    assert tracks.moving(TrackerConfig()).all()
    l4.track_class.update({201: ("building", 0.9), 202: ("vehicle", 0.9)})
    l4._remember_lost(tracks)
    building, vehicle = l4.lost.lost[201], l4.lost.lost[202]
    # the building is looked for where it stood, the vehicle along its way
    assert not building.moving and np.allclose(building.v_xy, 0.0)
    assert vehicle.moving and np.allclose(vehicle.v_xy, [2.0, 0.0])


def test_partial_view_does_not_make_a_static_wall_move() -> None:
    # more of a static wall comes into view each sweep: its visible centre moves 1 m a sweep
    cfg = TrackerConfig()
    speeds = {}
    for partial in (True, False):
        tr = Tracker(cfg)
        for k in range(8):
            t = k * SWEEP_NS
            length = 2.0 + 2.0 * k
            z = np.array([[length / 2, 0.0, 1.0]])
            m = Measurements(z, np.array([t]), _what(length))
            if not partial:  # the same measurements as if every view were whole
                tr.tracks.w[:, 0] = length
            tr.step(m, t)
        speeds[partial] = evident_speed(tr.tracks.x[0], tr.tracks.P[0], 2.0)
    assert speeds[False] > 3.0  # taken at face value the centre's drift is a speed
    # the view's growth widens R along the wall: the spurious speed is cut by about half
    # (not removed: a steady growth still looks like slow motion)
    assert speeds[True] < 0.6 * speeds[False]


def test_a_wall_sliding_into_view_is_classed_at_rest_a_mover_by_its_speed() -> None:
    # the partly seen wall above, its visible centre 1 m further each sweep, and a car
    # driving 8 m/s: the sequential test holds the wall at rest, so it shows no speed
    cfg = TrackerConfig()
    wall, car = Tracker(cfg), Tracker(cfg)
    for k in range(8):
        t = k * SWEEP_NS
        length = 2.0 + 2.0 * k
        wall.step(Measurements(np.array([[length / 2, 0.0, 1.0]]), np.array([t]), _what(length)), t)
        x = 8.0 * t / 1e9
        car.step(Measurements(np.array([[x, 5.0, 0.8]]), np.array([t]), _what(4.5, 1.8)), t)
    assert evident_speed(wall.tracks.x[0], wall.tracks.P[0], 2.0) > 0.5  # the filter's drift
    assert wall.tracks.tested_speed(cfg)[0] == 0.0
    assert car.tracks.tested_speed(cfg)[0] > 5.0


def test_partial_view_R_grows_along_the_long_axis_only() -> None:
    cfg = TrackerConfig()
    yaw = math.radians(30.0)
    base = measurement_R(_what(6.0, yaw=yaw), cfg)[0]
    R = measurement_R(_what(6.0, yaw=yaw), cfg, _what(10.0, yaw=yaw))[0]
    u = np.array([math.cos(yaw), math.sin(yaw)])
    n = np.array([-u[1], u[0]])
    assert u @ (R - base)[:2, :2] @ u == pytest.approx(4.0)  # (half the 4 m change)^2
    assert n @ (R - base)[:2, :2] @ n == pytest.approx(0.0, abs=1e-12)
    assert np.all(np.linalg.eigvalsh(R) > 0)


def test_evident_speed_is_zero_within_the_uncertainty() -> None:
    x = np.array([0, 0, 0, 1.0, 0, 0])
    assert evident_speed(x, np.eye(6) * 1.0, 2.0) == 0.0
    assert evident_speed(x, np.eye(6) * 0.01, 2.0) == pytest.approx(0.8)


def test_a_one_sweep_blob_gets_no_frame_and_no_event() -> None:
    kd = kd_store.open(":memory:")
    cfg = SPConfig(egosphere=EgosphereConfig(n_rows=64, n_cols=1024, max_returns=1))
    sp = KDSensoryProcessor(kd, cfg)
    wall = _wall_world(15.0)
    r0 = sp.process(_moving_sweep(wall, 0, 0.0), _pose(0, 0.0))
    assert not r0.objects and not kd.events(class_name="appeared")
    assert (r0.entity_images[4] >= 0).sum() == 0
    assert r0.attention_mask is not None
    r1 = sp.process(_moving_sweep(wall, SWEEP_NS, 0.0), _pose(SWEEP_NS, 0.0))
    assert len(r1.objects) == 1  # seen twice: a hypothesis with a frame
    obj = kd.get(r1.objects[0])
    assert obj.status == kd_store.Status.HYPOTHESIZED
    assert kd.events(class_name="appeared", participant=obj.id)


# ---------------------------------------------------------------- camera appearance

R_WORLD_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _camera(depth_m: float | None = None, t_ns: int = 0) -> tuple[CameraFrame, np.ndarray]:
    """A 256 x 256 camera at the world origin looking along +x; the image's left half (world
    +y) is grey 200, its right half 50."""
    img = np.full((256, 256), 50, np.uint8)
    img[:, :128] = 200
    K = np.array([[128.0, 0.0, 127.5], [0.0, 128.0, 127.5], [0.0, 0.0, 1.0]])
    depth = None if depth_m is None else np.full((256, 256), depth_m, np.float32)
    T = np.eye(4)
    T[:3, :3] = R_WORLD_OPTICAL
    return CameraFrame(t_ns, "camera", img, K, depth), T


def test_appearance_is_the_mean_grey_where_the_returns_land() -> None:
    cam, T = _camera()
    left = np.c_[np.full(5, 10.0), np.linspace(1.0, 2.0, 5), np.zeros(5)]
    right = left * [1, -1, 1]
    behind = left * [-1, 1, 1]
    pts = np.vstack([left, right, behind])
    ids = np.repeat([1, 2, 3], 5)
    a = object_appearance(pts, ids, cam, T)
    assert a.ids.tolist() == [1, 2]  # nothing of object 3 is in front of the camera
    np.testing.assert_allclose(a.intensity, [200 / 255, 50 / 255])
    np.testing.assert_allclose(a.coverage, [1.0, 1.0])
    assert np.isnan(a.excess_green).all()  # a grey image has no colour to tell
    # with a depth image, returns hidden behind something nearer are not counted
    cam_near, _ = _camera(depth_m=5.0)
    assert object_appearance(pts, ids, cam_near, T).ids.size == 0


def test_appearance_of_a_colour_image_per_object_as_counted_one_by_one() -> None:
    """Many objects with large, unsorted ids on a colour image: each object's grey is the
    mean over its seen returns of the mean of the three channels at the pixel it lands on,
    its coverage the share seen and its excess green the sum of 2G - R - B over the sum of
    R + G + B at those pixels; the same as counting one object at a time."""
    rng = np.random.default_rng(7)
    cam, T = _camera()
    img = rng.integers(0, 256, size=(256, 256, 3), dtype=np.uint8)
    cam = CameraFrame(0, "camera", img, cam.K, None)
    n = 4000
    # in front, beside and behind the camera, so some returns of most objects are not seen
    pts = np.c_[rng.uniform(-5.0, 30.0, n), rng.uniform(-20.0, 20.0, n), rng.uniform(-3, 3, n)]
    ids = rng.choice([9_000_017, 12, 4_500_000_001, 77, 300], size=n)
    a = object_appearance(pts, ids, cam, T)
    K = cam.K
    want = {}
    for oid in np.unique(ids):
        p = pts[ids == oid]
        x_opt, y_opt, z_opt = -p[:, 1], -p[:, 2], p[:, 0]  # R_WORLD_OPTICAL's inverse
        front = z_opt > 1e-3
        u = K[0, 0] * x_opt / np.where(front, z_opt, 1.0) + K[0, 2]
        v = K[1, 1] * y_opt / np.where(front, z_opt, 1.0) + K[1, 2]
        on = front & (u >= -0.5) & (u < 255.5) & (v >= -0.5) & (v < 255.5)
        px = np.array([img[round(vv), round(uu)].astype(float) for uu, vv in
                       zip(u[on], v[on], strict=True)]).reshape(-1, 3)  # fmt: skip
        if len(px) >= 3:
            exg = (2 * px[:, 1] - px[:, 0] - px[:, 2]).sum() / px.sum()
            want[int(oid)] = (px.mean() / 255, on.mean(), exg)
    assert a.ids.tolist() == sorted(want)
    assert len(want) >= 4
    np.testing.assert_allclose(a.intensity, [want[i][0] for i in sorted(want)], rtol=1e-12)
    np.testing.assert_allclose(a.coverage, [want[i][1] for i in sorted(want)], rtol=1e-12)
    np.testing.assert_allclose(a.excess_green, [want[i][2] for i in sorted(want)], rtol=1e-12)


def test_excess_green_tells_leaves_from_stone_in_any_light() -> None:
    """A leafy green object and a grey-brown one, each under full light, in shade (a third of
    it) and overexposed twice as bright: the grey value follows the light, the excess green
    stays with the surface."""
    cam, T = _camera()
    left = np.c_[np.full(5, 10.0), np.linspace(1.0, 2.0, 5), np.zeros(5)]  # left half
    pts, ids = np.vstack([left, left * [1, -1, 1]]), np.repeat([1, 2], 5)
    leaf, stone = np.array([60.0, 110.0, 40.0]), np.array([100.0, 95.0, 85.0])
    green, grey = [], []
    for light in (1.0, 1.0 / 3.0, 2.0):
        img = np.empty((256, 256, 3), np.uint8)
        img[:, :128] = np.clip(leaf * light, 0, 255)
        img[:, 128:] = np.clip(stone * light, 0, 255)
        a = object_appearance(pts, ids, CameraFrame(0, "camera", img, cam.K, None), T)
        green.append(a.excess_green)
        grey.append(a.intensity)
    green = np.array(green)
    np.testing.assert_allclose(green[:, 0], 120 / 210, atol=0.03)  # leaves: (220 - 100) / 210
    np.testing.assert_allclose(green[:, 1], 5 / 280, atol=0.03)  # stone: about none
    assert np.ptp(np.array(grey)[:, 0]) > 0.2  # while the grey value moved with the light
    # black pixels carry no colour: no excess green rather than a division by zero
    dark = CameraFrame(0, "camera", np.zeros((256, 256, 3), np.uint8), cam.K, None)
    assert np.isnan(object_appearance(pts, ids, dark, T).excess_green).all()


def test_pipeline_writes_camera_appearance_of_confirmed_objects() -> None:
    kd = kd_store.open(":memory:")
    cfg = SPConfig(egosphere=EgosphereConfig(n_rows=64, n_cols=1024, max_returns=1))
    sp = KDSensoryProcessor(kd, cfg)
    wall = _wall_world(15.0)
    wall = wall[wall[:, 1] > 0.5]  # only the left half: all of it lands on grey 200
    cam, T_cam = _camera()
    T_cam[2, 3] = 1.8
    for k in range(6):
        t = k * SWEEP_NS
        r = sp.process(_moving_sweep(wall, t, 0.0), _pose(t, 0.0), camera=cam, T_world_camera=T_cam)
    obj = kd.get(r.objects[0])
    assert obj.status == kd_store.Status.CONFIRMED
    assert obj.attributes["camera_intensity"].observed == pytest.approx(200 / 255)
    assert obj.attributes["camera_coverage"].observed > 0.5
    assert "camera_excess_green" not in obj.attributes  # a grey camera shows no colour
    assert "height_m" in obj.attributes  # the LADAR attributes are kept beside it
    # a colour camera: the wall is a green hedge, its excess green in the KD and in the
    # attributes it is classified by
    hedge = np.zeros((256, 256, 3), np.uint8)
    hedge[:] = (40, 90, 30)
    cam = CameraFrame(0, "camera", hedge, cam.K, None)
    r = sp.process(_moving_sweep(wall, 6 * SWEEP_NS, 0.0), _pose(6 * SWEEP_NS, 0.0), camera=cam,
                   T_world_camera=T_cam)  # fmt: skip
    obj = kd.get(r.objects[0])
    assert obj.attributes["camera_excess_green"].observed == pytest.approx(110 / 160)
    assert sp.level4.appearance_of(r.objects[0])["camera_excess_green"] == pytest.approx(110 / 160)
    # a broken camera frame is skipped, the sweep's result kept
    bad = CameraFrame(0, "camera", np.zeros((4, 4), np.uint8), np.eye(3) * 0.0)
    r = sp.process(_moving_sweep(wall, 7 * SWEEP_NS, 0.0), _pose(7 * SWEEP_NS, 0.0), camera=bad,
                   T_world_camera=T_cam)  # fmt: skip
    assert r.ok and r.objects


def _pair_walking(config: TrackerConfig) -> Tracker:
    """One person walking along x, joined after 0.5 s by a second 0.7 m beside her."""
    tr = Tracker(config)
    for k in range(12):
        t = k * SWEEP_NS
        x = 1.4 * t * 1e-9
        xy = [[x, 0.0, 0.9]] + ([[x, 0.7, 0.9]] if k >= 5 else [])
        n = len(xy)
        tr.step(Measurements(np.array(xy), np.full(n, t), np.vstack([_what(0.6, 0.5)] * n)), t)
    return tr


def test_two_people_walking_close_together_are_two_tracks() -> None:
    # a small body's footprint is known to a few cm: the margin that takes pieces of a
    # partly seen car or wall is a fraction of the body's size, so a person 0.7 m beside a
    # confirmed one is not taken for a piece of her
    tr = _pair_walking(TrackerConfig())
    assert (tr.tracks.status == TrackStatus.CONFIRMED).sum() == 2
    one = _pair_walking(TrackerConfig(part_margin_frac=1.0)).tracks  # a flat 0.5 m margin
    assert (one.status == TrackStatus.CONFIRMED).sum() == 1


def _parked_car_then_neighbour(tracker: Tracker) -> np.ndarray:
    """A parked car (4.5 x 1.8 m, its length along x) at y = 0 confirmed at rest, its visible
    centre wandering across it as the view changes (0.1 m a sweep for the last 6 sweeps),
    then unseen for a sweep, then a segment of the car parked beside it, 3 m on: the step's
    track_of (the parked car's track is track 0)."""
    what = np.array([[4.5, 1.8, 1.5, 0.0]])
    y = [0.05 * ((-1) ** k) for k in range(20)] + [0.1 + 0.1 * k for k in range(6)]
    for k, yk in enumerate(y):
        t = k * SWEEP_NS
        tracker.step(Measurements(np.array([[20.0, yk, 0.75]]), np.array([t]), what), t)
    tr = tracker.tracks
    assert tr.status[0] == TrackStatus.CONFIRMED and not tr.moving(tracker.config)[0]
    t = (len(y) + 1) * SWEEP_NS
    beyond = Measurements(np.array([[20.0, 3.0, 0.75]]), np.array([t]), what)
    track_of, _ = tracker.step(beyond, t)
    return track_of


def test_a_parked_car_is_gated_where_it_rests_not_where_its_centre_drifted() -> None:
    track_of = _parked_car_then_neighbour(Tracker())
    assert track_of[0] != 0  # the car beside it is a new track, not the parked one moved

    class VelocityGated(Tracker):
        def _gated_states(self, x_pred, P_pred, t_ns):
            return x_pred, P_pred

    # gated on its constant-velocity prediction, the parked car's track took it
    assert _parked_car_then_neighbour(VelocityGated())[0] == 0
