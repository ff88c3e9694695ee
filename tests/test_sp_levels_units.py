"""Unit tests of SP levels 2-5: each grouping rule, the filters, confirm/deny, the classifier,
groups, and the consistency of entity images with the KD's frames (against analytic truth)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

import kd_store
from kd_store import Level, Status
from logs.types import LadarScan
from sp.classify import Classifier
from sp.computation import ground_below, segment_attributes
from sp.context import IMAGE_NAMES, SPConfig
from sp.ground import GroundConfig, ground_mask
from sp.groups import group_labels, match_groups
from sp.segments import label_objects, range_edges
from sp.tracking import (
    F_Q,
    Measurements,
    Tracker,
    TrackerConfig,
    TrackStatus,
    predict,
    update,
)
from sp.windowing import window_mask
from wm.entities import KDSensoryProcessor

H, W = 32, 360
EL = np.deg2rad(np.linspace(2.0, -25.0, H))  # row 0 highest
AZ = np.pi - (np.arange(W) + 0.5) * 2 * np.pi / W
SENSOR_H = 1.8


def _rays() -> np.ndarray:
    E, A = np.meshgrid(EL, AZ, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)


def flat_scene(
    box_xy: tuple[float, float] | None = (10.0, 0.0),
    half: float = 1.0,
    top: float = 1.5,
    slope: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast a plane z = -SENSOR_H + slope * x and an axis-aligned box standing on it.
    Returns (xyz (H, W, 3), valid (H, W), truth_box (H, W) bool)."""
    d = _rays()
    # plane: t * dz = -h + slope * t * dx  ->  t = -h / (dz - slope * dx)
    den = d[..., 2] - slope * d[..., 0]
    with np.errstate(divide="ignore"):
        t = np.where(den < -1e-6, -SENSOR_H / den, np.inf)
    t = np.where(t < 80.0, t, np.inf)
    hit_box = np.zeros((H, W), dtype=bool)
    if box_xy is not None:
        z0 = -SENSOR_H + slope * box_xy[0]
        lo = np.array([box_xy[0] - half, box_xy[1] - half, z0])
        hi = np.array([box_xy[0] + half, box_xy[1] + half, z0 + top])
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (lo - 0 * d) / d
            t1 = (hi - 0 * d) / d
        tmin = np.nanmax(np.minimum(t0, t1), axis=-1)
        tmax = np.nanmin(np.maximum(t0, t1), axis=-1)
        hit = (tmax >= tmin) & (tmin > 0) & (tmin < t)
        t = np.where(hit, tmin, t)
        hit_box = hit
    valid = np.isfinite(t)
    xyz = np.where(valid[..., None], d * np.where(valid, t, 0)[..., None], np.nan)
    return xyz, valid, hit_box


# ---------------------------------------------------------------- grouping rules


@pytest.mark.parametrize("slope", [0.0, 0.15])
def test_ground_is_the_plane_and_not_the_box(slope: float) -> None:
    xyz, valid, box = flat_scene(slope=slope)
    ground, h = ground_mask(xyz, valid, GroundConfig())
    assert abs(h - SENSOR_H) < 0.2
    plane = valid & ~box
    assert np.count_nonzero(ground & plane) >= 0.97 * np.count_nonzero(plane)
    # the box's foot (its lowest 20 cm) is where box and ground meet; above it, nothing is ground
    above = box & (xyz[..., 2] > -SENSOR_H + slope * xyz[..., 0] + 0.2)
    assert np.count_nonzero(above) > 50
    assert np.count_nonzero(ground & above) == 0


def test_curb_is_stepped_over() -> None:
    xyz, valid, _ = flat_scene(box_xy=None)
    r = np.hypot(xyz[..., 0], xyz[..., 1])
    xyz[..., 2] += np.where(r > 8.0, 0.12, 0.0)  # a 12 cm curb 8 m out
    ground, _ = ground_mask(xyz, valid)
    assert np.count_nonzero(ground) >= 0.97 * np.count_nonzero(valid)


def _columns(profile: list[tuple[float, float]], n_cols: int = 90) -> tuple[np.ndarray, np.ndarray]:
    """An image whose every column holds the returns ``profile`` ((range m, height m) from the
    sensor, in order of rising elevation, bottom row first), at azimuths around the sensor."""
    rows = len(profile)
    az = np.linspace(-np.pi, np.pi, n_cols, endpoint=False)
    r = np.array([p[0] for p in profile])[::-1, None]  # row 0 is the highest
    z = np.array([p[1] for p in profile])[::-1, None]
    xyz = np.stack(np.broadcast_arrays(r * np.cos(az), r * np.sin(az), z), axis=-1)
    return np.ascontiguousarray(xyz, dtype=np.float64), np.ones((rows, n_cols), dtype=bool)


NEAR_GROUND = [(2.0 + 0.5 * k, -SENSOR_H) for k in range(6)]  # 2 .. 4.5 m
CAR_FACE = [(5.0, z) for z in (-1.6, -1.3, -1.0, -0.7, -0.4)]  # a parked car's side, 1.4 m


def test_a_gentle_resume_rule_tells_the_roof_of_a_car_behind_a_car_from_ground() -> None:
    # a sweep sees over the first parked car only the roof of the one behind it: a flat run
    # 1.3 m above the ground 13-15 m out, rising 5.5 degrees from the ground before the first
    roof = [(13.0 + 0.5 * k, -0.5) for k in range(5)]
    xyz, valid = _columns(NEAR_GROUND + CAR_FACE + roof)
    on_roof = np.zeros(valid.shape, dtype=bool)
    on_roof[: len(roof)] = True
    gentle, _ = ground_mask(xyz, valid, GroundConfig())
    assert gentle[-len(NEAR_GROUND) :].all()
    assert not gentle[on_roof].any()
    # a steeper rule takes it for ground
    steep, _ = ground_mask(
        xyz, valid, GroundConfig(resume_slope_deg=15.0, resume_max_rise_m=math.inf)
    )
    assert steep[on_roof].all()


def test_the_roof_of_a_car_in_the_row_behind_is_not_ground() -> None:
    # a parking lot: over the first parked car a sweep sees the roof of one in the next row,
    # 1.3 m above the ground 14.6 m past the last ground return (5.1 degrees), and the roofs
    # of that row beyond it: none of them is ground
    roofs = [(19.1, -0.5), (25.0, -0.4), (31.0, -0.35), (37.0, -0.3)]
    xyz, valid = _columns(NEAR_GROUND + CAR_FACE + roofs)
    ground, _ = ground_mask(xyz, valid, GroundConfig())
    assert not ground[: len(roofs)].any()
    assert ground[-len(NEAR_GROUND) :].all()
    # the former 5 degree rule took the row for ground, and 3 degrees without a cap on the
    # rise the roofs 31 m and more out (both from the car's foot, which the walk then took
    # for ground: no foot rule either)
    former = GroundConfig(foot_rise_m=math.inf, resume_max_rise_m=math.inf)
    five, _ = ground_mask(xyz, valid, replace(former, resume_slope_deg=5.0))
    assert five[: len(roofs)].all()
    three, _ = ground_mask(xyz, valid, former)
    assert three[:2].all() and not three[2:4].any()


def test_gentle_hill_behind_a_car_is_ground() -> None:
    hill = [(r, -SENSOR_H + (r - 6.0) * math.tan(math.radians(3.0))) for r in range(8, 21, 2)]
    xyz, valid = _columns(NEAR_GROUND + CAR_FACE + hill)
    ground, _ = ground_mask(xyz, valid, GroundConfig())
    face = slice(len(hill), len(hill) + len(CAR_FACE) - 1)  # the face above its foot
    assert ground[: len(hill)].all() and not ground[face].any()


def test_contiguity_groups_the_box_and_separates_two() -> None:
    xyz, _, box = flat_scene(box_xy=(10.0, 0.0))
    xyz2, _, box2 = flat_scene(box_xy=(10.0, 5.0))
    both = box | box2
    xyz = np.where(box2[..., None], xyz2, xyz)
    rng = np.linalg.norm(np.nan_to_num(xyz), axis=-1)
    labels = label_objects(xyz, rng, both, np.deg2rad(27 / 31), 2 * np.pi / W)
    a, b = np.unique(labels[box]), np.unique(labels[box2])
    assert a.size == 1 and b.size == 1 and a[0] != b[0] and a[0] >= 0
    assert np.all(labels[~both] == -1)


def test_speckle_below_min_pixels_is_not_grouped() -> None:
    xyz = np.zeros((H, W, 3))
    xyz[..., 0] = 10.0
    mask = np.zeros((H, W), dtype=bool)
    mask[5, 5] = True
    labels = label_objects(xyz, np.full((H, W), 10.0), mask, 0.01, 0.01)
    assert labels[5, 5] == -1


def test_range_edges_mark_the_near_side_of_a_jump() -> None:
    r = np.full((4, 10), 20.0)
    r[:, 4:7] = 5.0
    edge = range_edges(r, np.ones_like(r, dtype=bool))
    assert edge[:, 4].all() and edge[:, 6].all()
    assert not edge[:, 5].any() and not edge[:, 0].any()


def test_computation_of_box_attributes() -> None:
    xyz, valid, box = flat_scene(box_xy=(10.0, 0.0), half=1.0, top=1.5)
    ground, _ = ground_mask(xyz, valid)
    labels = np.where(box, 0, -1)
    z = np.where(valid, xyz[..., 2], np.nan)
    a = segment_attributes(
        labels,
        np.nan_to_num(xyz),
        np.zeros((H, W)),
        np.linalg.norm(np.nan_to_num(xyz), axis=-1),
        np.zeros((H, W), np.int64),
        ground_below(ground, z),
    )
    assert len(a) == 1
    assert a.height_m[0] == pytest.approx(1.5, abs=0.2)
    assert a.ground_z_m[0] == pytest.approx(-SENSOR_H, abs=0.1)
    assert a.center_xyz[0, 1] == pytest.approx(0.0, abs=0.3)
    assert 9.0 <= a.center_xyz[0, 0] <= 10.0  # the visible face is at x = 9


def test_degenerate_segments_do_not_crash() -> None:
    labels = np.full((2, 3), -1)
    labels[0, 0] = 0  # one pixel
    labels[1, :] = 1  # collinear
    pts = np.zeros((2, 3, 3))
    pts[1, :, 0] = [1.0, 2.0, 3.0]
    a = segment_attributes(
        labels,
        pts,
        np.zeros((2, 3)),
        np.ones((2, 3)),
        np.zeros((2, 3), np.int64),
        np.full((2, 3), np.nan),
    )
    assert np.all(np.isfinite(a.center_xyz)) and a.length_m[0] == 0.0
    assert a.length_m[1] == pytest.approx(2.0)


# ---------------------------------------------------------------- filtering


def test_batched_kalman_equals_filterpy() -> None:
    rng = np.random.default_rng(1)
    kf = KalmanFilter(dim_x=6, dim_z=3)
    x0 = rng.normal(size=6)
    A = rng.normal(size=(6, 6))
    P0 = A @ A.T + np.eye(6)
    dt = 0.1
    F, Q = F_Q(np.array([dt]), 2.0)
    kf.x, kf.P, kf.F, kf.Q = x0.copy(), P0.copy(), F[0], Q[0]
    kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
    R = np.diag([0.1, 0.2, 0.3])
    kf.R = R
    z = rng.normal(size=3)
    kf.predict()
    kf.update(z)
    x, P = predict(x0[None], P0[None], np.array([dt]), 2.0)
    x, P, nis = update(x, P, z[None], R[None])
    np.testing.assert_allclose(x[0], kf.x, atol=1e-10)
    np.testing.assert_allclose(P[0], kf.P, atol=1e-10)
    assert nis[0] == pytest.approx(float(kf.y @ np.linalg.solve(kf.S, kf.y)))


def _meas(xyz: np.ndarray, t_ns: int) -> Measurements:
    xyz = np.atleast_2d(xyz)
    return Measurements(xyz, np.full(len(xyz), t_ns), np.tile([4.0, 2.0, 1.5, 0.0], (len(xyz), 1)))


def test_consistent_track_is_confirmed_and_velocity_estimated() -> None:
    tr = Tracker(TrackerConfig())
    for k in range(15):
        tr.step(_meas([5.0 * 0.1 * k, 0.0, 0.0], k * 100_000_000), k * 100_000_000)
    assert len(tr.tracks) == 1
    assert tr.tracks.status[0] == TrackStatus.CONFIRMED
    assert tr.tracks.x[0, 3] == pytest.approx(5.0, abs=0.3)
    P = tr.tracks.P[0]
    np.testing.assert_allclose(P, P.T)
    assert np.all(np.linalg.eigvalsh(P) > 0)


def test_one_off_hypothesis_is_denied_and_lost_track_gone() -> None:
    cfg = TrackerConfig()
    tr = Tracker(cfg)
    tr.step(_meas([0.0, 0.0, 0.0], 0), 0)
    for k in range(1, cfg.max_misses_hyp + 2):
        tr.step(_meas(np.zeros((0, 3)), 0), k * 100_000_000)
    assert tr.tracks.status[0] == TrackStatus.DENIED
    done = tr.drop_finished()
    assert len(done) == 1 and len(tr.tracks) == 0
    # a confirmed track left unseen goes
    for k in range(6):
        tr.step(_meas([0.0, 0.0, 0.0], k * 100_000_000), k * 100_000_000)
    assert tr.tracks.status[0] == TrackStatus.CONFIRMED
    for k in range(6, 6 + cfg.max_misses + 1):
        tr.step(_meas(np.zeros((0, 3)), 0), k * 100_000_000)
    assert tr.tracks.status[0] == TrackStatus.GONE


def test_assignment_keeps_two_crossing_tracks_apart() -> None:
    tr = Tracker()
    for k in range(10):
        t = k * 100_000_000
        tr.step(_meas([[0.1 * k, 0.0, 0.0], [0.1 * k, 6.0, 0.0]], t), t)
    assert len(tr.tracks) == 2
    assert sorted(np.round(tr.tracks.x[:, 1])) == [0.0, 6.0]


# ---------------------------------------------------------------- classification, groups


def test_classifier_picks_the_prototype_and_its_lineage() -> None:
    lib = kd_store.ClassLibrary.default(fitted=False)  # written-down prototypes score 1 at home
    clf = Classifier(lib, Level.OBJECT)
    for name in ("vehicle", "person", "building", "tree", "post"):
        m = clf.classify(dict(lib.get(name).attributes))
        assert m.name == name and m.score == pytest.approx(1.0)
        assert m.generic[-1] == name
    m = clf.classify({"height_m": 8.0, "width_m": 4.0, "length_m": 4.0, "speed_mps": 0.0})
    assert m.generic == ("vegetation", "tree")


def test_groups_by_proximity_and_common_motion() -> None:
    pos = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [0.0, 50.0], [2.0, 50.0]])
    vel = np.array([[5.0, 0.0], [5.2, 0.0], [5.0, 0.1], [0.0, 0.0], [3.0, 0.0]])
    lab = group_labels(pos, vel, np.zeros(5, dtype=bool))
    assert lab[0] == lab[1] == lab[2] >= 0
    assert lab[3] == lab[4] == -1  # one still, one moving: not alike
    carried, new, ended = match_groups(
        {7: frozenset({1, 2, 3})}, [frozenset({1, 2}), frozenset({9, 8})]
    )
    assert carried == {0: 7} and new == [1] and ended == []


def test_windows_grow_with_uncertainty() -> None:
    row_el = EL.copy()
    c = np.array([[20.0, 0.0, -1.0]])
    small = window_mask((H, W), c, np.array([0.1]), row_el)
    big = window_mask((H, W), c, np.array([2.0]), row_el)
    assert small.any() and np.count_nonzero(big) > np.count_nonzero(small)
    assert np.all(big[small])


# ---------------------------------------------------------------- the pipeline and the KD


def _scan_of(xyz: np.ndarray, valid: np.ndarray, t_ns: int) -> LadarScan:
    pts = xyz[valid].astype(np.float32)
    ring = (H - 1 - np.nonzero(valid)[0]).astype(np.uint16)
    n = pts.shape[0]
    return LadarScan(t_ns, "ladar", pts, np.ones(n, np.float32), np.zeros(n, np.int64), ring)


def test_pipeline_images_point_to_frames_and_back() -> None:
    from sp.egosphere import EgosphereConfig
    from sp.pipeline import SPConfig

    kd = kd_store.open(":memory:")
    cfg = SPConfig(egosphere=EgosphereConfig(n_rows=H, n_cols=W, max_returns=1))
    sp = KDSensoryProcessor(kd, cfg)
    T = np.eye(4)
    T[2, 3] = SENSOR_H
    result = None
    for k in range(6):
        xyz, valid, _ = flat_scene(box_xy=(10.0 + 0.5 * k, 0.0))
        result = sp.process(_scan_of(xyz, valid, k * 100_000_000), T)
        assert result.ok
    assert result is not None
    img4 = result.entity_images[4]
    ids = np.unique(img4[img4 >= 0])
    assert ids.size == 1
    obj = kd.get(int(ids[0]))
    assert obj.level == Level.OBJECT and IMAGE_NAMES[4] in obj.images
    assert obj.status == Status.CONFIRMED
    assert obj.state.velocity_xyz[0] == pytest.approx(5.0, abs=1.0)
    assert obj.state.position_xyz[2] == pytest.approx(0.75, abs=0.3)  # half the box height
    img3 = result.entity_images[3]
    g = np.unique(img3[result.ground_mask])
    assert g.size == 1 and kd.get(int(g[0])).level == Level.SURFACE
    assert np.all(img3[result.ground_mask] >= 0)
    # the box's front is a vertical face: a level-3 surface, part of the object, on its pixels
    faces = np.unique(img3[(img3 >= 0) & ~result.ground_mask])
    assert faces.size == 1
    face = kd.get(int(faces[0]))
    assert face.level == Level.SURFACE and IMAGE_NAMES[3] in face.images
    assert kd.parent(face.id) == obj.id
    assert np.all(img4[img3 == face.id] == obj.id)
    assert "wall" in face.generic_classes
    # its contact with the ground is a level-2 list lying on the ground, just above it
    contact = [i for i in kd.parts(face.id) if kd.get(i).level == Level.LIST]
    assert len(contact) == 1
    assert g[0] in kd.pointers(contact[0], "on_top_of")
    rows, _ = np.nonzero(result.entity_images[2] == contact[0])
    assert rows.size and np.all(result.ground_mask[rows + 1, _])
    img2 = result.entity_images[2]
    for lid in np.unique(img2[img2 >= 0]):
        lst = kd.get(int(lid))
        assert lst.level == Level.LIST and IMAGE_NAMES[2] in lst.images
        owner = kd.parent(int(lid))
        assert owner is not None
        assert np.any((img2 == lid) & ((img4 == owner) | (img3 == owner)))
    # per-point views agree with the images
    flat = img4.reshape(-1)[result.point_pixel]
    np.testing.assert_array_equal(flat, result.point_entity_ids)
    assert kd.events(class_name="confirmed", participant=obj.id)
    assert kd.events(class_name="appeared", participant=obj.id)


def test_a_failing_sweep_is_skipped_and_tracks_kept() -> None:
    kd = kd_store.open(":memory:")
    from sp.egosphere import EgosphereConfig
    from sp.pipeline import SPConfig

    sp = KDSensoryProcessor(
        kd, SPConfig(egosphere=EgosphereConfig(n_rows=H, n_cols=W, max_returns=1))
    )
    T = np.eye(4)
    T[2, 3] = SENSOR_H
    for k in range(4):
        xyz, valid, _ = flat_scene()
        sp.process(_scan_of(xyz, valid, k * 100_000_000), T)
    n = len(sp.tracker.tracks)
    bad = LadarScan(
        500_000_000,
        "ladar",
        np.zeros((3, 2), np.float32),
        np.zeros(3, np.float32),
        np.zeros(3, np.int64),
    )
    r = sp.process(bad, T)
    assert not r.ok and sp.n_failed == 1 and len(sp.tracker.tracks) == n
    assert math.isfinite(float(sp.tracker.tracks.x.sum()))


def test_sp_places_returns_where_the_caller_deskewed_them(caplog) -> None:
    """One deskew per cycle: given the sweep's world points (as the node fused them into its
    maps), SP's world points are exactly those, wherever its own per-column model would have
    put them; an array that is not one point per return skips the sweep, saying why."""
    from sp.egosphere import EgosphereConfig
    from sp.pipeline import SPConfig

    kd = kd_store.open(":memory:")
    sp = KDSensoryProcessor(
        kd, SPConfig(egosphere=EgosphereConfig(n_rows=H, n_cols=W, max_returns=1))
    )
    T = np.eye(4)
    T[2, 3] = SENSOR_H
    xyz, valid, _ = flat_scene()
    scan = _scan_of(xyz, valid, 0)
    # the caller's deskew moved every return 0.3 m along x (a vehicle creeping mid-sweep)
    world = scan.points_xyz.astype(np.float64) + T[:3, 3] + np.array([0.3, 0.0, 0.0])
    r = sp.process(scan, T, points_world=world)
    assert r.ok
    np.testing.assert_allclose(r.points_world, world[r.point_index], atol=1e-6)
    own = KDSensoryProcessor(
        kd_store.open(":memory:"),
        SPConfig(egosphere=EgosphereConfig(n_rows=H, n_cols=W, max_returns=1)),
    ).process(scan, T)
    assert np.allclose(own.points_world[:, 0] + 0.3, r.points_world[:, 0], atol=1e-5)
    bad = sp.process(_scan_of(xyz, valid, 100_000_000), T, points_world=world[:-1])
    assert not bad.ok and "points_world has shape" in caplog.text


def test_placing_the_callers_points_fills_every_pixel_with_a_return_in_any_layout() -> None:
    """Each pixel with a return takes its return's point, the others keep theirs, whether the
    (H, W, 3) array is C-contiguous or a strided view."""
    from types import SimpleNamespace

    from sp.level1 import _place

    rng = np.random.default_rng(3)
    index = np.full((8, 16, 2), -1, np.int32)
    index[..., 0].reshape(-1)[rng.permutation(128)[:90]] = rng.permutation(100)[:90]
    img = SimpleNamespace(point_index=index)
    pw = rng.random((100, 3))
    want = np.full((8, 16, 3), -7.0)
    has = index[..., 0] >= 0
    want[has] = pw[index[..., 0][has]]
    dense = np.full((8, 16, 3), -7.0)
    strided = np.full((3, 8, 16), -7.0).transpose(1, 2, 0)
    for xyz_w in (dense, strided):
        _place(xyz_w, img, pw, 100)
        np.testing.assert_array_equal(xyz_w, want)


def test_level2_lists_are_confirmed_by_persistence_and_denied_when_not_seen_again() -> None:
    """A list starts hypothesized; seen three sweeps running it is confirmed, while one seen
    once and never again is denied after its confidence decays below the deny threshold."""
    kd = kd_store.open(":memory:")
    sp = KDSensoryProcessor(kd)
    tc = sp.config.tracker
    lids = [
        kd.add_entity(f"list {i}", Level.LIST, status=Status.HYPOTHESIZED, confidence=0.3).id
        for i in range(2)
    ]
    sp.level2.ids = np.array(lids, dtype=np.int64)
    sp.level2.conf = np.full(2, tc.confidence0)
    sp.level2.hits = np.zeros(2, dtype=np.int64)
    sp.level2.open = np.ones(2, dtype=bool)
    sp.level2.key = np.array([4 * 7, 4 * 7 + 1], dtype=np.int64)  # owner 7, two kinds
    sp.level2.dead = np.zeros(2, dtype=bool)
    sp.level2.lut[[28, 29]] = [0, 1]
    sp.level2.lists_of[7] = list(lids)
    statuses = []
    for sweep in range(8):
        sp.level2.filter(np.array([0, 1] if sweep == 0 else [0]))
        sp.write_pending()  # the world model's entity update
        statuses.append((kd.get(lids[0]).status, kd.get(lids[1]).status))
    assert [s[0] for s in statuses[:2]] == [Status.HYPOTHESIZED] * 2
    assert statuses[2][0] == Status.CONFIRMED and kd.get(lids[0]).confidence >= tc.confirm
    first_denied = next(k for k, s in enumerate(statuses) if s[1] == Status.DENIED)
    assert 2 <= first_denied <= 6 and kd.get(lids[1]).confidence < tc.deny
    assert statuses[-1] == (Status.CONFIRMED, Status.DENIED)
    # the denied list is no longer its owner's, and its (owner, kind) would start a new one
    assert sp.level2.lists_of[7] == [lids[0]] and sp.level2.lut[29] == -1
    assert sp.level2.lut[28] == 0


def _height_field_scene(height, shapes=()) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the terrain z = -SENSOR_H + height(x, y) (marched in 2 cm steps to 40 m) and
    ``shapes``, functions (points (..., 3)) -> inside (...) bool, standing on it.
    Returns xyz (H, W, 3) (NaN where nothing is hit) and valid (H, W)."""
    d = _rays()
    t = np.arange(0.5, 40.0, 0.02)
    p = d[:, :, None, :] * t[None, None, :, None]  # (H, W, T, 3)
    inside = p[..., 2] <= -SENSOR_H + height(p[..., 0], p[..., 1])
    for shape in shapes:
        inside |= shape(p)
    hit = inside.any(axis=-1)
    first = np.argmax(inside, axis=-1)
    xyz = np.where(hit[..., None], d * t[first][..., None], np.nan)
    return xyz, hit


def _rise_of(
    xyz: np.ndarray, valid: np.ndarray, chord_m: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """SP's ground, its grouping of the rest, and :func:`foot_rise_deg` of those segments
    (steps up to ``chord_m`` apart; None: the configured ``foot_chord_m``)."""
    from sp.level3_surfaces import foot_rise_deg

    ground, _ = ground_mask(xyz, valid, GroundConfig())
    rng = np.linalg.norm(np.nan_to_num(xyz), axis=-1)
    labels = label_objects(
        np.nan_to_num(xyz), np.where(valid, rng, np.inf), valid & ~ground,
        EL[0] - EL[1], 2 * np.pi / W,
    )  # fmt: skip
    K = int(labels.max()) + 1
    cfg = SPConfig()
    chord_m = cfg.foot_chord_m if chord_m is None else chord_m
    return foot_rise_deg(labels, np.nan_to_num(xyz), valid, ground, K, 2, chord_m, cfg.foot_rise_m)


def _ridge(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A bank 0.8 m high across the way 7 m ahead, its face 45 degrees steep."""
    return np.clip(x - 7.0, 0.0, 0.8) * (np.abs(y) < 6.0)


def _car_at(x_m: float):
    """Inside test of a 2 m x 2 m x 1.5 m box standing on the flat ground ``x_m`` ahead."""

    def shape(p: np.ndarray) -> np.ndarray:
        return (
            (np.abs(p[..., 0] - x_m) < 1.0)
            & (np.abs(p[..., 1]) < 1.0)
            & (p[..., 2] < -SENSOR_H + 1.5)
        )

    return shape


def test_a_bank_rises_from_the_ground_as_ground_does() -> None:
    xyz, valid = _height_field_scene(_ridge)
    rise, n = _rise_of(xyz, valid)
    assert rise.size >= 1 and n.max() >= 10  # steeper than the ground's slope limit: grouped
    biggest = int(np.argmax(n))
    assert 35.0 < rise[biggest] < 55.0


@pytest.mark.parametrize("kind", ["car", "bush"])
def test_an_object_rises_steeply_from_the_ground_or_leans_over_it(kind: str) -> None:
    flat = lambda x, y: 0.0 * x  # noqa: E731
    if kind == "car":  # a 1.5 m box on the ground 8 m ahead
        shape = _car_at(9.0)
    else:  # a flat ellipsoid, 15 % of its height below the ground, as bushes and rocks stand

        def shape(p):
            q = (p - np.array([9.0, 0.0, -SENSOR_H + 0.35 * 0.9])) / np.array([1.2, 1.0, 0.45])
            return (q**2).sum(axis=-1) <= 1.0

    xyz, valid = _height_field_scene(flat, [shape])
    rise, n = _rise_of(xyz, valid)
    biggest = int(np.argmax(n))
    assert n[biggest] >= SPConfig().foot_min_columns  # enough columns to be judged
    assert rise[biggest] > 70.0


def test_a_foot_the_beams_do_not_resolve_is_not_judged() -> None:
    from sp.level3_surfaces import foot_rise_deg

    # 32 m out the rows lie far apart: a return 1.1 m from the ground return below it and its
    # next 1.1 m further up cannot tell a slanted face from a gentle rise, so no column counts
    xyz = np.zeros((3, 4, 3))
    xyz[2, :, 0], xyz[2, :, 2] = 32.1, -1.38  # ground (the lowest row)
    xyz[1, :, 0], xyz[1, :, 2] = 33.0, -0.67  # the segment's foot ...
    xyz[0, :, 0], xyz[0, :, 2] = 33.9, -0.07  # ... and its next return up
    labels = np.array([[0] * 4, [0] * 4, [-1] * 4])
    ground = labels < 0
    valid = np.ones((3, 4), dtype=bool)
    rise, n = foot_rise_deg(labels, xyz, valid, ground, 1, 2, 0.6, 0.4)
    assert n[0] == 0 and np.isnan(rise[0])
    rise, n = foot_rise_deg(labels, xyz, valid, ground, 1, 2, 2.0, 0.4)
    assert n[0] == 4 and 33.0 < rise[0] < 35.0


def test_a_body_above_the_ground_is_not_a_bank() -> None:
    # a car's body 0.3 m over the road: the chord from the road to the body's lowest return
    # is gentle, but the body rises upright from there. This test image's rows lie far apart
    # on the road, so steps up to 2 m count here (at the configured 0.25 m none would)
    def body(p: np.ndarray) -> np.ndarray:
        return _car_at(9.0)(p) & (p[..., 2] > -SENSOR_H + 0.3)

    xyz, valid = _height_field_scene(lambda x, y: 0.0 * x, [body])
    rise, n = _rise_of(xyz, valid, chord_m=2.0)
    biggest = int(np.argmax(n))
    assert n[biggest] >= SPConfig().foot_min_columns
    assert rise[biggest] > 70.0
