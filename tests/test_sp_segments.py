"""Level-4 grouping (sp.segments) on hand-built scenes ray-cast on a 64 x 1024 egosphere.

Truth is the box each ray hits first (analytic slab test); the ground plane is left out of
the mask, as the pipeline does.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from kernel_scenes import non_ground, segment_scene

from sp.segments import (
    SegmentConfig,
    SegmentError,
    _join_near_pieces,
    _links,
    _range_step,
    label_objects,
    label_objects_reference,
    merge_behind_occluders,
    merge_collinear,
    merge_grazing,
    split_at_gap,
)

H, W = 64, 1024
EL = np.deg2rad(np.linspace(3.0, -25.0, H))  # row 0 highest
AZ = np.pi - (np.arange(W) + 0.5) * 2 * np.pi / W
ROW_STEP, COL_STEP = float(EL[0] - EL[1]), 2 * np.pi / W
SENSOR_H = 1.8


def cast(boxes: list[tuple[tuple[float, ...], tuple[float, ...]]], rows: np.ndarray | None = None):
    """Ray-cast axis-aligned boxes (lo xyz, hi xyz; sensor frame, ground at z = -SENSOR_H).

    Returns xyz (H, W, 3), range (H, W) (inf where nothing is hit), hit (H, W) int64 index of
    the box hit first, -1 ground or nothing. ``rows``: (H,) bool rows that fire (others empty).
    """
    E, A = np.meshgrid(EL, AZ, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[..., 2] < -1e-6, -SENSOR_H / d[..., 2], np.inf)
        hit = np.full((H, W), -1, dtype=np.int64)
        for k, (lo, hi) in enumerate(boxes):
            t0, t1 = np.array(lo) / d, np.array(hi) / d
            tmin = np.nanmax(np.minimum(t0, t1), axis=-1)
            tmax = np.nanmin(np.maximum(t0, t1), axis=-1)
            h = (tmax >= tmin) & (tmin > 0) & (tmin < t)
            t = np.where(h, tmin, t)
            hit[h] = k
    t = np.where(t < 80.0, t, np.inf)
    if rows is not None:
        t[~rows] = np.inf
        hit[~rows] = -1
    xyz = np.where(np.isfinite(t)[..., None], d * np.where(np.isfinite(t), t, 0)[..., None], 0.0)
    return xyz, t, hit


def segments_of(boxes, config: SegmentConfig | None = None, rows=None):
    xyz, rng, hit = cast(boxes, rows)
    labels = label_objects(xyz, rng, hit >= 0, ROW_STEP, COL_STEP, config)
    return labels, hit


def one_label(labels: np.ndarray, where: np.ndarray) -> int:
    """The single label covering ``where`` (fails when it is split or ungrouped)."""
    u = np.unique(labels[where])
    assert u.size == 1 and u[0] >= 0, f"labels {u} on one object"
    return int(u[0])


def apart(labels: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    """No segment holds pixels of both ``a`` and ``b``, and each is mostly one segment (a face
    seen at a grazing angle may come apart in pieces)."""
    la, lb = labels[a], labels[b]
    for lab in (la, lb):
        u, n = np.unique(lab, return_counts=True)
        assert u[np.argmax(n)] >= 0 and n.max() >= 0.9 * lab.size, f"{dict(zip(u, n, strict=True))}"
    return not set(la[la >= 0].tolist()) & set(lb[lb >= 0].tolist())


def wall(x_m: float = 7.0):
    """A building front ``x_m`` ahead, 12 m wide, 3.8 m tall."""
    return ((x_m, -6.0, -SENSOR_H), (x_m + 0.4, 6.0, 2.0))


WALL = wall()


def person(gap_m: float, x_m: float = 7.0):
    """A person-sized box (0.25 m deep, 0.5 m wide, 1.8 m tall) ``gap_m`` before the wall at
    ``x_m``: the range steps by gap_m + 0.25 m from its front to the wall."""
    x = x_m - gap_m
    return ((x - 0.25, -0.25, -SENSOR_H), (x, 0.25, 0.0))


@pytest.mark.parametrize("x_m", [7.0, 12.0, 20.0])
def test_person_in_front_of_a_wall_is_its_own_segment(x_m: float) -> None:
    labels, hit = segments_of([wall(x_m), person(0.3, x_m)])
    assert np.count_nonzero(hit == 1) > 20
    assert apart(labels, hit == 0, hit == 1)


def test_without_the_step_test_contiguity_joins_them() -> None:
    # the same scene with the range-step test off: the 0.6 m distance floor joins them
    labels, hit = segments_of([WALL, person(0.3)], SegmentConfig(step_m=0.0))
    assert one_label(labels, hit == 0) == one_label(labels, hit == 1)


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, 60.0])
def test_a_flat_wall_stays_one_segment(yaw_deg: float) -> None:
    # a thin wall through (12, 0), turned so the sensor sees it at a grazing angle too
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    pts = [(12.0 + c * 0.0 - s * u, s * 0.0 + c * u) for u in np.linspace(-5.0, 5.0, 41)]
    boxes = [((x - 0.15, y - 0.15, -SENSOR_H), (x + 0.15, y + 0.15, 1.0)) for x, y in pts]
    labels, hit = segments_of(boxes)
    assert np.count_nonzero(hit >= 0) > 300
    one_label(labels, hit >= 0)


def test_a_car_beside_a_car_stays_two() -> None:
    car_a = ((10.0, 0.3, -SENSOR_H + 0.2), (14.5, 2.1, -SENSOR_H + 1.5))
    car_b = ((10.0, -2.1, -SENSOR_H + 0.2), (14.5, -0.3, -SENSOR_H + 1.5))
    labels, hit = segments_of([car_a, car_b])
    assert apart(labels, hit == 0, hit == 1)


def test_a_car_parked_before_a_wall_is_its_own_segment() -> None:
    car = ((2.5, -3.0, -SENSOR_H + 0.2), (6.5, -1.2, -SENSOR_H + 1.5))  # 0.5 m before it
    labels, hit = segments_of([WALL, car])
    assert np.count_nonzero(hit == 1) > 200
    assert apart(labels, hit == 0, hit == 1)


def test_an_overhang_stays_joined_to_what_carries_it() -> None:
    # a tree: a trunk under a broad crown, whose lower face is nearer than the trunk
    trunk = ((10.0, -0.2, -SENSOR_H), (10.4, 0.2, 0.2))
    crown = ((9.7, -1.5, 0.2), (11.4, 1.5, 1.5))
    labels, hit = segments_of([trunk, crown])
    assert one_label(labels, hit == 0) == one_label(labels, hit == 1)


def test_empty_rows_between_beams_do_not_split_a_surface() -> None:
    fire = np.zeros(H, dtype=bool)
    fire[::3] = True  # two empty rows between beams, as an elevation-binned image has
    labels, hit = segments_of([WALL], rows=fire)
    one_label(labels, hit == 0)
    labels, _ = segments_of([WALL], SegmentConfig(row_gap=0), rows=fire)
    assert np.unique(labels[hit == 0]).size > 1


def test_a_see_through_object_far_out_is_one_segment() -> None:
    # a bicycle-like frame: two thin bars 0.5 m apart, each about a column wide at 20 m, with
    # the ground between them (not grouped) so no two bars are image neighbours
    def bars(x_m: float):
        lo, hi = -SENSOR_H + 0.3, -SENSOR_H + 1.0
        return [((x_m, y, lo), (x_m + 0.05, y + 0.13, hi)) for y in (0.0, 0.5)]

    cfg = SegmentConfig(min_pixels=1, near_m=0.6)
    labels, hit = segments_of(bars(20.0), cfg)
    assert np.count_nonzero(hit == 0) >= 4 and np.count_nonzero(hit == 1) >= 4
    one_label(labels, hit >= 0)
    labels, _ = segments_of(bars(20.0), dataclasses.replace(cfg, near_m=0.0))
    assert np.unique(labels[hit >= 0]).size == 2
    # nearer than near_min_range_m the beams are dense enough: proximity alone does not join
    labels, hit = segments_of(bars(10.0), cfg)
    assert np.unique(labels[hit >= 0]).size == 2


def test_bad_thresholds_are_refused() -> None:
    with pytest.raises(SegmentError, match="step_m -1"):
        SegmentConfig(step_m=-1.0)


def test_no_grouping_on_empty_or_degenerate_images() -> None:
    xyz = np.zeros((3, 5, 3))
    rng = np.full((3, 5), np.inf)
    assert (label_objects(xyz, rng, np.zeros((3, 5), bool), 0.01, 0.01) == -1).all()
    one_row = label_objects(np.ones((1, 5, 3)), np.ones((1, 5)), np.ones((1, 5), bool), 0.01, 0.1)
    assert (one_row == 0).all()


# ---------------------------------------------------------------- against plain loops


def _links_loop(mask: np.ndarray, di: int, dj: int, empty: np.ndarray) -> set[tuple[int, int]]:
    Hm, Wm = mask.shape
    out = set()
    for i in range(Hm - di):
        for j in range(Wm):
            j2 = (j + dj) % Wm
            if mask[i, j] and mask[i + di, j2] and all(empty[i + k, j] for k in range(1, di)):
                out.add((i * Wm + j, (i + di) * Wm + j2))
    return out


@pytest.mark.parametrize("di,dj", [(0, 1), (0, 2), (1, 0), (2, 0), (3, 0)])
def test_links_match_a_loop(di: int, dj: int) -> None:
    rng = np.random.default_rng(di * 10 + dj)
    for _ in range(20):
        shape = (int(rng.integers(1, 7)), int(rng.integers(1, 9)))
        if di >= shape[0]:
            continue
        empty = rng.random(shape) < 0.4
        mask = ~empty & (rng.random(shape) < 0.8)
        a, b = _links(mask, di, dj, empty)
        assert set(zip(a.tolist(), b.tolist(), strict=True)) == _links_loop(mask, di, dj, empty)


def _step_loop(r: np.ndarray, a: int, b: int, di: int, dj: int, cfg: SegmentConfig) -> bool:
    Hm, Wm = r.shape

    def at(i: int, j: int) -> float:
        if not 0 <= i < Hm:
            return np.nan
        v = r[i, j % Wm]
        return v if np.isfinite(v) and v > 0 else np.nan

    (ia, ja), (ib, jb) = divmod(a, Wm), divmod(b, Wm)
    ra, rb = at(ia, ja), at(ib, jb)
    s = rb - ra
    sides = [ra - at(ia - di, ja - dj), at(ib + di, jb + dj) - rb]
    if not all(np.isfinite(x) for x in [*sides, s]):
        return False
    thr = cfg.step_m + cfg.step_frac * min(ra, rb)
    cut = abs(s) > thr and min(abs(s - x) - abs(x) for x in sides) > thr
    return cut and (di == 0 or s < 0)


@pytest.mark.parametrize("di,dj", [(0, 1), (0, 2), (1, 0), (2, 0)])
def test_range_step_matches_a_loop(di: int, dj: int) -> None:
    cfg = SegmentConfig()
    rng = np.random.default_rng(7 + di + dj)
    for _ in range(20):
        shape = (int(rng.integers(di + 1, 8)), int(rng.integers(2, 10)))
        r = 10.0 + rng.choice([0.0, 0.5, 1.0], size=shape) + 0.05 * rng.standard_normal(shape)
        r[rng.random(shape) < 0.2] = np.inf  # no return
        r[rng.random(shape) < 0.05] = 0.0
        a, b = _links(np.ones(shape, bool), di, dj, np.zeros(shape, bool))
        got = _range_step(r.reshape(-1), a, b, di, dj, shape, cfg)
        want = [_step_loop(r, int(x), int(y), di, dj, cfg) for x, y in zip(a, b, strict=True)]
        assert got.tolist() == want


def _components(labels: np.ndarray) -> set[frozenset[int]]:
    return {frozenset(np.flatnonzero(labels == k).tolist()) for k in np.unique(labels)}


def _root(parent: list[int], k: int) -> int:
    while parent[k] != k:
        k = parent[k]
    return k


def test_join_near_pieces_matches_pairwise_distances() -> None:
    cfg = SegmentConfig(near_pixels=3, near_m=0.5)
    rng = np.random.default_rng(3)
    for _ in range(20):
        n = int(rng.integers(1, 30))
        comp = rng.integers(0, max(n // 2, 1), size=n)
        comp = np.unique(comp, return_inverse=True)[1]
        pts = rng.uniform(0.0, 3.0, size=(n, 3))
        r = rng.uniform(10.0, 20.0, size=n)
        got = _join_near_pieces(comp, pts, r, cfg)
        # reference: union of small far pieces whose points come within near_m, by a loop
        small = (np.bincount(comp)[comp] < cfg.near_pixels) & (r > cfg.near_min_range_m)
        parent = list(range(comp.max() + 1))
        for i in range(n):
            for j in range(i + 1, n):
                close = np.linalg.norm(pts[i] - pts[j]) <= cfg.near_m
                if small[i] and small[j] and close:
                    parent[_root(parent, int(comp[i]))] = _root(parent, int(comp[j]))
        want = np.array([_root(parent, int(c)) for c in comp])
        assert _components(got) == _components(want)


# ---------------------------------------------------------------- line continuity


def test_line_continuity_does_not_take_a_person_beside_the_wall() -> None:
    # a wall along x in two pieces, a thin third piece on its line, a person 0.4 m before it
    centers = np.array([[0.0, 0.0], [6.0, 0.0], [9.5, 0.05], [9.5, -0.45]])
    length = np.array([5.0, 5.0, 1.0, 0.6])
    width = np.array([0.2, 0.2, 0.15, 0.5])
    lab = merge_collinear(centers, np.zeros(4), length, width, np.full(4, 12.0))
    assert lab[0] == lab[1] == lab[2]
    assert lab[3] != lab[0]


def test_line_continuity_does_not_take_a_car_parked_along_the_wall() -> None:
    # a wall piece on the line, then a car (front and side: 4.5 m by 1.8 m) just past its end
    centers = np.array([[0.0, 0.0], [5.5, 0.3], [10.0, 0.0]])
    length = np.array([5.0, 4.5, 5.0])
    width = np.array([0.2, 1.8, 0.2])
    lab = merge_collinear(centers, np.zeros(3), length, width, np.full(3, 12.0))
    assert lab[1] not in (lab[0], lab[2])


def _footprints(labels: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each segment's xy centre (K, 2) and half diagonal (K,), m."""
    K = int(labels.max()) + 1
    c, r = np.zeros((K, 2)), np.zeros(K)
    for k in range(K):
        p = xyz[labels == k][:, :2]
        lo, hi = p.min(axis=0), p.max(axis=0)
        c[k], r[k] = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    return c, r


def _walkers(x_m: float = 12.0):
    """Two bodies (0.25 x 0.5 x 1.8 m) shoulder to shoulder, one a step (0.3 m) behind."""
    a = ((x_m, -0.6, -SENSOR_H), (x_m + 0.25, -0.1, 0.0))
    b = ((x_m + 0.3, -0.1, -SENSOR_H), (x_m + 0.55, 0.4, 0.0))
    return [a, b]


def test_a_segment_holding_two_predicted_people_is_cut_between_them() -> None:
    """Proximity joins two walkers side by side; their tracks' predicted places cut them
    apart again, every return going to its own body."""
    from sp.segments import split_by_predictions

    xyz, rng, hit = cast(_walkers())
    labels = label_objects(xyz, rng, hit >= 0, ROW_STEP, COL_STEP)
    assert one_label(labels, hit >= 0) == 0  # joined
    centres = np.array([[12.12, -0.35], [12.42, 0.15]])
    out = split_by_predictions(labels, xyz, centres, *_footprints(labels, xyz), 0.4, 0.5, 4)
    assert apart(out, hit == 0, hit == 1)
    assert np.unique(out[hit == 0]).size == 1 and np.unique(out[hit == 1]).size == 1


def test_one_prediction_close_or_tiny_parts_leave_a_segment_whole() -> None:
    """One predicted person, two predictions closer than min_apart_m (one walker tracked
    twice), or a prediction that would take fewer than min_pixels returns: no cut."""
    from sp.segments import split_by_predictions

    xyz, rng, hit = cast(_walkers())
    labels = label_objects(xyz, rng, hit >= 0, ROW_STEP, COL_STEP)
    for centres in ([[12.12, -0.35]], [[12.12, -0.35], [12.2, -0.1]]):
        out = split_by_predictions(
            labels, xyz, np.array(centres), *_footprints(labels, xyz), 0.4, 0.5, 4
        )
        assert out is labels
    centres = np.array([[12.12, -0.35], [12.42, 0.15]])
    foot = _footprints(labels, xyz)
    assert split_by_predictions(labels, xyz, centres, *foot, 0.4, 0.5, 10_000) is labels


# ---------------------------------------------------------------- faces at a grazing angle


def _grazing_merge(boxes, collinear: bool = True):
    """label_objects, then merge_grazing and (``collinear``) merge_collinear on the segments'
    attributes, as the pipeline runs them (sensor at the origin, ground at z = -SENSOR_H);
    returns (labels before, labels after, hit)."""
    from sp.computation import segment_attributes

    xyz, rng, hit = cast(boxes)
    labels = label_objects(xyz, rng, hit >= 0, ROW_STEP, COL_STEP)
    zeros = np.zeros((H, W), dtype=np.float32)
    rng0, t_off = np.where(np.isfinite(rng), rng, 0.0), np.zeros((H, W), np.int64)
    ground_z = np.full((H, W), -SENSOR_H)

    def attrs(lab):
        return segment_attributes(lab, xyz, zeros, rng0, t_off, ground_z)

    def relabel(lab, new):
        return np.where(lab >= 0, new[np.maximum(lab, 0)], -1)

    a = attrs(labels)
    top = a.ground_z_m + a.height_m
    out = relabel(labels, merge_grazing(a.center_xyz[:, :2], a.width_m, top, np.zeros(2), COL_STEP))
    if not collinear:
        return labels, out, hit
    a = attrs(out)
    out = relabel(
        out, merge_collinear(a.center_xyz[:, :2], a.yaw_rad, a.length_m, a.width_m, a.range_m)
    )
    return labels, out, hit


def _share_of_largest(labels: np.ndarray, where: np.ndarray) -> float:
    u, n = np.unique(labels[where], return_counts=True)
    return float(n[u >= 0].max() / where.sum())


def test_a_face_seen_at_a_grazing_angle_is_one_segment_again() -> None:
    # a building side running away from the sensor 3 m to its left: seen at 6-17 degrees
    side = ((10.0, 3.0, -SENSOR_H), (28.0, 3.3, 4.0))
    before, after, hit = _grazing_merge([side])
    face = hit == 0
    assert np.unique(before[face & (before >= 0)]).size >= 4  # strips along the line of sight
    assert _share_of_largest(after, face) >= 0.9


def test_grazing_pieces_do_not_take_a_person_or_a_post_before_them() -> None:
    side = ((10.0, 3.0, -SENSOR_H), (28.0, 3.3, 4.0))
    walker = ((14.0, 2.2, -SENSOR_H), (14.3, 2.7, 0.0))  # 0.3 m off the face, 0.5 m wide
    post = ((20.0, 2.5, -SENSOR_H), (20.1, 2.6, -0.6))  # 0.1 m thick, 1.2 m tall
    _, after, hit = _grazing_merge([side, walker, post], collinear=False)
    for k in (1, 2):
        assert not set(after[hit == k].tolist()) & set(after[hit == 0].tolist()), k


def test_strips_side_by_side_across_the_line_of_sight_stay_apart() -> None:
    # two poles at the same range, a column apart in azimuth but not along the ray
    centers = np.array([[20.0, 0.0], [20.0, 0.12]])
    lab = merge_grazing(centers, np.full(2, 0.05), np.full(2, 2.0), np.zeros(2), COL_STEP)
    assert lab[0] != lab[1]
    # the same two strips one behind the other along the ray are one face
    centers = np.array([[20.0, 0.0], [21.5, 0.0]])
    lab = merge_grazing(centers, np.full(2, 0.05), np.full(2, 2.0), np.zeros(2), COL_STEP)
    assert lab[0] == lab[1]


def test_scenes_exercise_every_rule():
    """The scenes the kernel harness holds label_objects to its reference on
    (test_kernel_equivalence.py) mean something only if each rule changes the labels
    somewhere."""
    changed = {"row_gap": 0, "step_m": 0, "near_pixels": 0, "min_pixels": 0}
    off = {"row_gap": 0, "step_m": 0.0, "near_pixels": 0, "min_pixels": 1}
    base = SegmentConfig(min_pixels=4)
    for seed, (h, w) in itertools.product(range(3), [(16, 1024), (64, 1024)]):
        xyz, rng, valid, row_step, col_step = segment_scene(seed, h, w)
        mask = non_ground(xyz, valid, seed)
        ref = label_objects_reference(xyz, rng, mask, row_step, col_step, base)
        for name, value in off.items():
            cfg = dataclasses.replace(base, **{name: value})
            other = label_objects_reference(xyz, rng, mask, row_step, col_step, cfg)
            changed[name] += int(not np.array_equal(ref, other))
    assert all(n > 0 for n in changed.values()), changed


def _side_by_side(gap_m: float, x_m: float = 10.0):
    """Two bodies (0.3 x 0.5 x 1.8 m) abreast across the line of sight, ``gap_m`` apart."""
    a = ((x_m, -0.5 - gap_m / 2, -SENSOR_H), (x_m + 0.3, -gap_m / 2, 0.0))
    b = ((x_m, gap_m / 2, -SENSOR_H), (x_m + 0.3, 0.5 + gap_m / 2, 0.0))
    return [a, b]


def _gap_split(labels: np.ndarray, xyz: np.ndarray, length_m: float) -> np.ndarray:
    K = int(labels.max()) + 1
    ones = np.ones(K)
    return split_at_gap(
        labels, xyz, ones * math.pi / 2, ones * length_m, ones * 0.3, ones * 1.8,
        0.25, 2.6, 0.9, 1.0, 8,
    )  # fmt: skip


def test_two_people_joined_by_proximity_are_cut_at_the_gap_between_them() -> None:
    xyz, _, hit = cast(_side_by_side(0.35))
    labels = np.where(hit >= 0, 0, -1)  # one segment, as proximity may join them
    out = _gap_split(labels, xyz, 1.35)
    assert apart(out, hit == 0, hit == 1)
    assert np.unique(out[hit == 0]).size == 1 and np.unique(out[hit == 1]).size == 1


def test_one_body_or_a_long_object_is_not_cut() -> None:
    xyz, _, hit = cast(_side_by_side(0.0))  # one body a metre wide: no gap
    labels = np.where(hit >= 0, 0, -1)
    assert _gap_split(labels, xyz, 1.0) is labels
    xyz, _, hit = cast(_side_by_side(0.35))  # the same returns on a car-length segment
    labels = np.where(hit >= 0, 0, -1)
    assert _gap_split(labels, xyz, 4.5) is labels


def _row(ranges: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """One scan row (1, n) of returns at ``ranges`` (m; inf = none) on successive columns of
    the 1024-column image, level with the sensor: xyz (1, n, 3) and range (1, n)."""
    r = np.array(ranges, dtype=np.float64)[None, :]
    az = AZ[: r.shape[1]][None, :]
    xyz = np.stack([np.cos(az), np.sin(az), np.zeros_like(az)], axis=-1)
    hit = np.isfinite(r)[..., None]
    return np.where(hit, xyz * np.nan_to_num(r, posinf=0.0)[..., None], 0.0), r


def _groups(ranges: list[float], grouped: list[bool]) -> list[int]:
    """Labels of a one-row scene by the compiled grouping, checked against the reference."""
    xyz, r = _row(ranges)
    mask = np.array(grouped)[None, :]
    cfg = SegmentConfig(min_pixels=1, near_pixels=0)
    got = label_objects(xyz, r, mask, ROW_STEP, COL_STEP, cfg)
    ref = label_objects_reference(xyz, r, mask, ROW_STEP, COL_STEP, cfg)
    assert _components(got) == _components(ref)
    return got[0].tolist()


# two cars parked nose to tail, seen past the corner of the first: its side recedes to 27 m,
# the second's begins at 28.4 m and recedes too. The first return of the second car is too far
# from the first car's corner for a next-column link, but the next-but-one link (twice the
# reach) from that corner would reach the second car's next return.
CAR_A = [25.0, 25.5, 26.0, 26.5, 27.0]
CAR_B = [28.9, 29.4, 29.9, 30.4]


def test_the_next_but_one_link_does_not_skip_a_return_between_two_objects() -> None:
    labels = _groups([*CAR_A, 28.4, *CAR_B], [True] * 10)
    assert len(set(labels[:5])) == 1 and len(set(labels[5:])) == 1
    assert labels[4] != labels[5]
    # the same scene with that return missing (a dropout): the link skips it and joins the cars
    labels = _groups([*CAR_A, np.inf, *CAR_B], [*[True] * 5, False, *[True] * 4])
    assert labels[4] == labels[6]
    # ... and a return behind both (the background seen through the gap) does not join them
    labels = _groups([*CAR_A, 45.0, *CAR_B], [True] * 10)
    assert labels[4] != labels[6]


def test_the_next_but_one_link_skips_an_occluder_in_front() -> None:
    # a wall at 20 m with a post 8 m out hiding one of its columns: the wall stays one piece
    wall_m = [20.0 + 0.02 * k for k in range(9)]
    ranges = [*wall_m[:4], 8.0, *wall_m[5:]]
    labels = _groups(ranges, [True] * 9)
    assert len({labels[k] for k in range(9) if k != 4}) == 1
    assert labels[4] != labels[3]


# --- continuity behind an occluder -------------------------------------------------------------


def behind_occluders(boxes, config: SegmentConfig | None = None):
    """Segments of a ray-cast scene after :func:`merge_behind_occluders`, with the truth hit."""
    xyz, rng, hit = cast(boxes)
    labels = label_objects(xyz, rng, hit >= 0, ROW_STEP, COL_STEP, config)
    new = merge_behind_occluders(labels, rng, COL_STEP, config)
    return labels, np.where(labels >= 0, new[np.maximum(labels, 0)], -1), hit


def car_face(x_m: float, y0: float, y1: float):
    """The side of a parked car ``x_m`` ahead from y0 to y1, 0.2-1.5 m above the ground (a
    slab, so the scene has no roof seen at a grazing angle)."""
    return ((x_m, y0, -SENSOR_H + 0.2), (x_m + 0.3, y1, -SENSOR_H + 1.5))


def person_at(x_m: float, y_m: float):
    return ((x_m - 0.25, y_m - 0.25, -SENSOR_H), (x_m, y_m + 0.25, 0.0))


def test_a_car_cut_in_two_by_a_person_in_front_is_one_segment_again() -> None:
    # a person 8 m out hides a metre of a car's side 16 m out: grouping alone leaves a piece of
    # the car each side of the person
    before, after, hit = behind_occluders([car_face(16.0, -2.0, 2.0), person_at(8.0, 0.0)])
    assert len(np.unique(before[hit == 0])) >= 2
    car = one_label(after, hit == 0)
    assert car != one_label(after, hit == 1)


def test_two_cars_behind_a_person_stay_apart_where_the_gap_between_them_shows() -> None:
    # the person hides the near end of car A and the edge of the 0.9 m gap; past it the rays
    # run through the gap (the far ground, or nothing), so nothing joins the cars
    cars = [car_face(16.0, 0.5, 2.5), car_face(16.0, -2.5, -0.4)]
    _, after, hit = behind_occluders([*cars, person_at(8.0, 0.4)])
    assert apart(after, hit == 0, hit == 1)
    assert one_label(after, hit == 2) not in set(after[(hit == 0) | (hit == 1)].tolist())


def test_pieces_at_ranges_that_do_not_continue_stay_apart() -> None:
    # a car 16 m out and one 19 m out, the person in front of where they meet in azimuth
    cars = [car_face(16.0, 0.0, 2.0), car_face(19.0, -2.4, 0.0)]
    _, after, hit = behind_occluders([*cars, person_at(8.0, 0.0)])
    assert apart(after, hit == 0, hit == 1)


def test_an_occluder_hiding_more_than_the_span_is_not_bridged() -> None:
    # a van 7 m out hides about 7 m of a wall 16 m out: too much to say what is behind it
    scene = [car_face(16.0, -6.0, 6.0), ((7.0, -1.5, -SENSOR_H), (9.0, 1.5, 0.2))]
    _, after, hit = behind_occluders(scene)
    assert len(np.unique(after[hit == 0])) == 2
    _, after, hit = behind_occluders(scene, SegmentConfig(hidden_span_m=10.0))
    one_label(after, hit == 0)
    _, after, hit = behind_occluders(
        [car_face(16.0, -2.0, 2.0), person_at(8.0, 0.0)], SegmentConfig(hidden_span_m=0.0)
    )
    assert len(np.unique(after[hit == 0])) == 2  # 0 turns the rule off


def test_the_run_wraps_in_azimuth_and_allows_a_dropout_but_not_a_gap() -> None:
    # one row: a surface at 16 m in columns W-4..W-1 (label 0) and 3..6 (label 1), an occluder
    # at 8 m in columns 0..2
    r = np.full((1, W), np.inf)
    labels = np.full((1, W), -1, dtype=np.int64)
    r[0, W - 4 :], r[0, 3:7], r[0, 0:3] = 16.0, 16.05, 8.0
    labels[0, W - 4 :], labels[0, 3:7], labels[0, 0:3] = 0, 1, 2
    assert merge_behind_occluders(labels, r, COL_STEP).tolist() == [0, 0, 1]
    r[0, 1] = np.inf  # a dropout inside the occluder
    assert merge_behind_occluders(labels, r, COL_STEP).tolist() == [0, 0, 1]
    r[0, 1], r[0, 2] = 8.0, np.inf  # no return next to the far piece: a gap may show there
    assert merge_behind_occluders(labels, r, COL_STEP).tolist() == [0, 1, 2]
    r[0, 2] = 30.0  # something behind the pieces seen past the occluder
    assert merge_behind_occluders(labels, r, COL_STEP).tolist() == [0, 1, 2]


def test_pieces_behind_one_of_their_group_stay_apart() -> None:
    # two people 10 m out with a third 0.7 m in front of them, between them in azimuth: people
    # walking together, not one surface behind an occluder; a post 3 m in front would be one
    r = np.full((1, W), np.inf)
    labels = np.full((1, W), -1, dtype=np.int64)
    r[0, 100:104], r[0, 104:108], r[0, 108:112] = 10.0, 9.3, 10.05
    labels[0, 100:104], labels[0, 104:108], labels[0, 108:112] = 0, 1, 2
    assert merge_behind_occluders(labels, r, COL_STEP).tolist() == [0, 1, 2]
    r[0, 104:108] = 7.0
    assert merge_behind_occluders(labels, r, COL_STEP).tolist() == [0, 1, 0]
