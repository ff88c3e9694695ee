"""Level-2 primitives (sp.lists), the batch classifier, class and value images (sp.images):
analytic truth, and every compiled kernel against its plain-numpy reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from kernel_reference.lists_reference import (
    block_moments_reference,
    list_slots_reference,
    list_sums_reference,
)

import kd_store
from kd_store import Level
from sp.classify import Classifier
from sp.images import ClassTable, LazyImages, class_values, value_images
from sp.lists import (
    ListConfig,
    ListKind,
    block_moments,
    brightness_edges,
    edge_branches,
    fill_slots,
    list_attributes,
    list_slots,
    list_slots_and_sums,
    list_sums,
    patch_grid,
    vertices,
)

RNG = np.random.default_rng(7)


# ---------------------------------------------------------------- kernels vs references


@pytest.mark.parametrize("shape", [(1, 1), (5, 7), (8, 32), (13, 50)])
@pytest.mark.parametrize("fill", [0.0, 0.3, 1.0])
def test_block_moments_match_numpy(shape: tuple[int, int], fill: float) -> None:
    xyz = RNG.normal(0.0, 20.0, (*shape, 3))
    mask = RNG.random(shape) < fill
    for bh, bw in ((4, 16), (2, 3), (1, 1)):
        got = block_moments(xyz, mask, bh, bw)
        ref = block_moments_reference(xyz, mask, bh, bw)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-9)
    assert np.isinf(block_moments(xyz, np.zeros(shape, bool), 2, 2)[:, 10]).all()


@pytest.mark.parametrize("seed", range(4))
def test_list_slots_and_sums_match_numpy(seed: int) -> None:
    g = np.random.default_rng(seed)
    H, W = 16, 40
    owner = g.integers(-1, 5, (H, W))
    r_edge = g.random((H, W)) < 0.2
    b_edge = (g.random((H, W)) < 0.2) & ~r_edge
    patch = g.random((H, W)) < 0.5
    lut = np.full(5 * 4 - 3, -1, np.int64)  # too short for the last owner's keys: missing
    lut[g.permutation(lut.size)[: lut.size // 2]] = np.arange(lut.size // 2)
    list_ids = np.arange(lut.size) * 3 + 100
    got = list_slots(owner, r_edge, b_edge, patch, lut, list_ids)
    ref = list_slots_reference(owner, r_edge, b_edge, patch, lut, list_ids)
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_array_equal(a, b)
    slots, ids, branches, missing = got
    assert (ids[slots >= 0] == list_ids[slots[slots >= 0]]).all() and (ids[slots < 0] == -1).all()
    # the lists of the missing keys are made: the waiting pixels get them
    full = np.full(max(lut.size, int(missing.max(initial=-1)) + 1), -1)
    full[: lut.size] = lut
    full[missing] = lut.size + np.arange(missing.size)
    more_ids = np.r_[list_ids, 1000 + np.arange(missing.size)]
    filled_slots, filled_ids = slots.copy(), ids.copy()
    fill_slots(filled_slots, filled_ids, full, more_ids)
    again = list_slots(owner, r_edge, b_edge, patch, full, more_ids)
    np.testing.assert_array_equal(filled_slots, again[0])
    np.testing.assert_array_equal(filled_ids, again[1])
    assert again[3].size == 0 and (again[0] >= -1).all()
    slots = filled_slots
    rng = g.uniform(1.0, 50.0, (H, W))
    rng[g.random((H, W)) < 0.1] = np.inf
    rng[g.random((H, W)) < 0.1] = np.nan
    inten = g.random((H, W)).astype(np.float32)  # float32 as the egosphere gives it
    inten[g.random((H, W)) < 0.1] = np.nan
    edge = r_edge | b_edge
    # the fused pass: the same slots, and the sums of the pixels whose list existed
    fused = list_slots_and_sums(owner, r_edge, b_edge, patch, lut, list_ids, rng, inten)
    for x, y in zip(fused[:4], got, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_allclose(
        fused[4],
        list_sums_reference(got[0], rng, inten, r_edge | b_edge, got[2], list_ids.size),
        rtol=1e-6,
        atol=1e-9,
    )
    n = int(slots.max()) + 1
    np.testing.assert_allclose(
        list_sums(slots, rng, inten, edge, branches, n),
        list_sums_reference(slots, rng, inten, edge, branches, n),
        rtol=1e-6,  # the kernel takes float32 intensity steps in float32, the reference in 64
        atol=1e-9,
    )


def test_list_slots_with_no_lists_and_no_edges() -> None:
    owner = np.full((3, 4), -1, np.int64)
    z = np.zeros((3, 4), bool)
    slots, ids, br, missing = list_slots(
        owner, z, z, z, np.zeros(0, np.int64), np.zeros(0, np.int64)
    )
    assert (slots == -1).all() and (ids == -1).all() and (br == 0).all() and missing.size == 0


# ---------------------------------------------------------------- edges and vertices


def test_edge_branches_of_line_t_and_cross() -> None:
    e = np.zeros((9, 9), bool)
    e[4, 1:8] = True  # a horizontal line
    b = edge_branches(e)
    assert b[4, 1] == 1 and b[4, 7] == 1 and (b[4, 2:7] == 2).all()
    e[5:8, 4] = True  # a stem down from its middle: a T
    b = edge_branches(e)
    assert b[4, 4] == 3 and b[7, 4] == 1
    e[1:4, 4] = True  # and up: a cross
    assert edge_branches(e)[4, 4] == 4
    lone = np.zeros((3, 3), bool)
    lone[1, 1] = True
    assert edge_branches(lone)[1, 1] == 0 and not vertices(edge_branches(lone)).any()
    assert vertices(edge_branches(e))[4, 4]


def test_brightness_edges_follow_a_painted_stripe_not_the_valid_border() -> None:
    H, W = 32, 120
    inten = np.full((H, W), 0.3, np.float32)
    inten[:, 50:70] = 0.8  # a bright stripe (paint) on a continuous surface
    valid = np.ones((H, W), bool)
    valid[:4] = False  # sky above row 4: its border is no brightness edge
    inten[~valid] = np.nan
    e = brightness_edges(inten, valid)
    cols = np.flatnonzero(e.any(axis=0))
    assert set(cols) <= {48, 49, 50, 51, 68, 69, 70, 71}
    assert e[10:28, 49:51].any(axis=1).all() and e[10:28, 69:71].any(axis=1).all()
    assert not e[:5].any()  # row 4 borders the sky
    assert not brightness_edges(np.full((H, W), 0.5), valid).any()


# ---------------------------------------------------------------- patches


def test_patch_grid_recovers_a_plane_normal_and_roughness() -> None:
    H, W = 16, 64
    az = np.linspace(-0.5, 0.5, W)
    el = np.linspace(-0.4, -0.05, H)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)
    n_true = np.array([0.2, 0.1, 1.0]) / np.linalg.norm([0.2, 0.1, 1.0])
    t = -2.0 / (d @ n_true)  # plane n . p = -2 (2 m below the sensor)
    xyz = d * t[..., None]
    g = patch_grid(xyz, np.ones((H, W), bool), ListConfig(patch_rows=4, patch_cols=8))
    assert g.ok.all() and g.shape == (4, 8)
    np.testing.assert_allclose(g.normal, np.tile(n_true, (g.n.size, 1)), atol=1e-9)
    assert g.roughness_m.max() < 1e-3  # one-pass moments: variance to ~1e-9 m^2
    noisy = xyz + RNG.normal(0.0, 0.02, xyz.shape) * n_true
    g2 = patch_grid(noisy, np.ones((H, W), bool), ListConfig(patch_rows=4, patch_cols=8))
    assert np.median(g2.roughness_m) == pytest.approx(0.02, rel=0.25)
    few = np.zeros((H, W), bool)
    few[0, :3] = True  # three pixels: no patch, no crash
    assert not patch_grid(xyz, few).ok.any()


def test_list_attributes_of_a_straight_range_edge() -> None:
    H, W = 8, 100
    slots = np.full((H, W), -1, np.int64)
    slots[1:7, 30] = 0  # the right side of an object at 10 m, 5 m before a far wall
    rng = np.full((H, W), 15.0)
    rng[:, :31] = 10.0
    edge = slots >= 0
    br = edge_branches(edge)
    inten = np.ones((H, W))
    a = list_attributes(list_sums(slots, rng, inten, edge, br, 1), 2 * math.pi / W, 1.0)
    assert a.ids.tolist() == [0] and a.n_pixels[0] == 6
    assert a.range_m[0] == pytest.approx(10.0)
    assert a.size_m[0] == pytest.approx(6 * 10.0 * 2 * math.pi / W)
    assert a.range_jump_m[0] == pytest.approx(5.0)
    assert a.orientation_rad[0] == pytest.approx(math.pi / 2, abs=1e-9)  # along a column
    assert a.edge_share[0] == 1.0 and a.vertex_share[0] == pytest.approx(2 / 6)  # two ends
    assert a.contrast[0] == 0.0


# ---------------------------------------------------------------- classification


def test_classify_many_equals_classify_and_ignores_missing() -> None:
    kd = kd_store.open(":memory:")
    for level in (Level.LIST, Level.SURFACE, Level.OBJECT):
        c = Classifier(kd.classes, level)
        names = sorted(c.mu)
        rows = []
        for _ in range(25):
            r = {a: float(RNG.uniform(0.0, 10.0)) for a in names if RNG.random() < 0.8}
            if r and RNG.random() < 0.3:
                r[next(iter(r))] = math.nan  # a missing attribute: NaN
            rows.append(r)
        rows.append({})
        for r, m in zip(rows, c.classify_many(rows), strict=True):
            one = c.classify(r)
            assert m.name == one.name and m.generic == one.generic
            assert m.score == pytest.approx(one.score, abs=1e-12)
            assert set(m.scores) == set(one.scores)


def test_list_prototypes_tell_the_kinds_apart() -> None:
    kd = kd_store.open(":memory:")
    c = Classifier(kd.classes, Level.LIST)
    typical = {
        "range_edge": {"edge_share": 1.0, "vertex_share": 0.1, "range_jump_m": 3.0,
                       "contrast": 0.2},
        "brightness_edge": {"edge_share": 1.0, "vertex_share": 0.1, "range_jump_m": 0.03,
                            "contrast": 0.6},
        "vertex": {"edge_share": 1.0, "vertex_share": 1.0, "range_jump_m": 1.0, "contrast": 0.3},
        "surface_patch": {"edge_share": 0.0, "vertex_share": 0.0, "range_jump_m": 0.08,
                          "contrast": 0.02},
    }  # fmt: skip
    for name, attrs in typical.items():
        assert c.classify(attrs).name == name


# ---------------------------------------------------------------- class and value images


def test_class_and_value_images_follow_the_entity_image_and_the_library() -> None:
    kd = kd_store.open(":memory:")
    names = [p.name for p in kd.classes]
    table = ClassTable()
    ids = np.array([3, 70, 5])
    table.set(ids, [names.index("wall"), names.index("vehicle"), -1])
    ent = np.full((4, 6), -1, np.int64)
    ent[0, :3] = 3
    ent[1] = 70
    ent[2, :2] = 5  # an entity without a class
    ent[3, 0] = 10_000  # an entity the table never saw
    cls = table.image(ent)
    assert cls.dtype == np.int32
    assert (cls[0, :3] == names.index("wall")).all() and (cls[1] == names.index("vehicle")).all()
    assert (cls[2] == -1).all() and (cls[3] == -1).all() and (cls[0, 3:] == -1).all()
    vals = value_images(cls, class_values(kd.classes, names))
    for n in ("cost", "risk", "worth_preserve"):
        assert vals[n].dtype == np.float32
        assert (vals[n][0, :3] == np.float32(getattr(kd.classes.get("wall").value, n))).all()
        assert (vals[n][1] == np.float32(getattr(kd.classes.get("vehicle").value, n))).all()
        assert np.isnan(vals[n][2:]).all()
    made = []
    lazy = LazyImages([2, 3], lambda k: made.append(k) or np.full(2, k))
    assert made == [] and list(lazy) == [2, 3]
    assert (lazy[3] == 3).all() and (lazy[3] == 3).all() and made == [3]
    with pytest.raises(KeyError):
        lazy[4]


def test_kinds_are_four() -> None:
    assert [k.value for k in ListKind] == [0, 1, 2, 3]
