"""The compiled level-2 passes of sp.lists against their references, exactly.

* range edges (:func:`range_jump_edges`, behind ``sp.segments.range_edges``) against the numpy
  form with ``np.roll`` (:func:`range_jump_edges_reference`);
* the fused slots-and-sums pass (:func:`list_slots_and_sums`) against the numpy slots
  (:func:`list_slots_reference`) and the per-pixel sums kernel (:func:`list_sums`, which adds the
  same float64 values in the same order: the sums are compared bit for bit) and, within
  1e-12, the numpy sums (:func:`list_sums_reference`, another summation order).

On synthetic sweeps built like the simulator's (ground, walls seen at grazing angles, cars,
poles, foliage of scattered ranges, sky and dropped returns, painted stripes and NaN in the
intensity), on small images, and on degenerate ones (all invalid, all valid, one pixel).
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from kernel_reference.lists_reference import list_slots_reference, list_sums_reference

from sp.lists import (
    brightness_edges,
    list_slots,
    list_slots_and_sums,
    list_sums,
    range_jump_edges,
    range_jump_edges_reference,
)
from sp.segments import SegmentConfig, range_edges

SENSOR_H = 1.8
GROUND = 500  # owner id of the ground in the synthetic owner images


@dataclasses.dataclass
class Sweep:
    """A synthetic LADAR sweep as SP level 2 gets it.

    range_m:   (H, W) float32 metres, inf where empty (and NaN, 0 or -1 at some empty pixels:
               every form of "no return"), 1 to 80 m where valid;
    valid:     (H, W) bool;
    intensity: (H, W) float32 reflectance-like units, NaN where empty;
    owner:     (H, W) int64 object (0..), ground (GROUND) or -1 (none, or an unowned return).
    """

    range_m: np.ndarray
    valid: np.ndarray
    intensity: np.ndarray
    owner: np.ndarray


def sweep(seed: int, H: int = 64, W: int = 1024) -> Sweep:
    """A sweep of ground, boxes (walls, cars, people, poles) and foliage seen from 1.8 m."""
    g = np.random.default_rng(seed)
    el = np.linspace(np.radians(3.0), np.radians(-25.0), H)[:, None] * np.ones((1, W))
    az = (np.arange(W)[None, :] + 0.5) * (2 * np.pi / W) * np.ones((H, 1))
    with np.errstate(divide="ignore"):
        rng = np.where(el < -1e-3, SENSOR_H / np.sin(-el), np.inf)  # the flat ground
    rng = rng * (1.0 + g.normal(0.0, 0.003, (H, W)))  # range noise
    owner = np.where(np.isfinite(rng), GROUND, -1)
    refl = np.where(np.isfinite(rng), 0.2, np.nan)
    # painted stripes on the ground (lane markings: a step in brightness, not in range)
    for _ in range(g.integers(2, 5)):
        a0 = g.uniform(0, 2 * np.pi)
        stripe = (np.abs(((az - a0) + np.pi) % (2 * np.pi) - np.pi) < g.uniform(0.01, 0.05)) & (
            owner == GROUND
        )
        refl[stripe] = g.uniform(0.5, 0.9)
    # boxes: an azimuth span, a top elevation, a range at one end and a slope along azimuth
    # (a wall at a grazing angle); poles thin and far; people and cars near
    boxes = []
    for kind, n in (("wall", g.integers(3, 7)), ("car", g.integers(3, 9)), ("pole", 8)):
        for _ in range(n):
            a0 = g.uniform(0, 2 * np.pi)
            if kind == "wall":
                span, r0, slope, top = g.uniform(0.2, 1.2), g.uniform(8, 60), g.uniform(-8, 8), 12
            elif kind == "car":
                span, r0, slope, top = g.uniform(0.05, 0.4), g.uniform(3, 25), 0.0, 1.6
            else:
                span, r0, slope, top = g.uniform(0.003, 0.02), g.uniform(10, 75), 0.0, 4
            boxes.append((a0, span, r0, slope, top))
    for k, (a0, span, r0, slope, top) in enumerate(boxes):
        da = (az - a0) % (2 * np.pi)
        r = np.clip(r0 + slope * da, 1.0, 80.0)
        top_el = np.arctan2(top - SENSOR_H, r)
        hit = (da < span) & (el <= top_el) & (r < rng)
        rng = np.where(hit, r * (1.0 + g.normal(0.0, 0.002, (H, W))), rng)
        owner = np.where(hit, k, owner)
        refl = np.where(hit, g.uniform(0.05, 0.8), refl)
    # foliage: ranges scattered by metres (a range edge at most pixels), its own owner
    for _ in range(g.integers(1, 3)):
        a0, span = g.uniform(0, 2 * np.pi), g.uniform(0.1, 0.4)
        hit = ((az - a0) % (2 * np.pi) < span) & (el > np.radians(-12))
        r = g.uniform(4.0, 12.0, (H, W))
        rng = np.where(hit, r, rng)
        owner = np.where(hit, len(boxes), owner)
        refl = np.where(hit, g.uniform(0.1, 0.4, (H, W)), refl)
    rng = np.where(rng > 80.0, np.inf, rng)
    valid = np.isfinite(rng)
    valid &= g.random((H, W)) > 0.03  # dropped returns
    valid[g.random(H) < 0.05] = False  # rows that did not fire
    owner = np.where(valid, owner, -1)
    owner[valid & (g.random((H, W)) < 0.02)] = -1  # returns in no object
    rng = np.where(valid, rng, np.inf).astype(np.float32)
    # the other forms of "no return" on a few empty pixels
    empty = np.flatnonzero(~valid.ravel())
    for v in (np.nan, 0.0, -1.0):
        rng.ravel()[g.choice(empty, size=min(empty.size, 20), replace=False)] = v
    inten = (refl * 1000.0 / np.maximum(np.where(valid, rng, 1.0), 1.0) ** 0.5).astype(np.float32)
    inten = inten * (1.0 + g.normal(0.0, 0.05, (H, W))).astype(np.float32)
    inten[~valid] = np.nan
    return Sweep(rng, valid, inten, owner.astype(np.int64))


SEEDS = range(5)
SMALL = [(1, 1), (1, 7), (6, 1), (2, 2), (3, 5), (7, 33)]


def small_sweep(seed: int, H: int, W: int) -> Sweep:
    """A small image with steps, NaN and empty pixels everywhere (every border case)."""
    g = np.random.default_rng(seed)
    rng = g.choice([2.0, 2.2, 5.0, 30.0, 31.0, 79.0], (H, W)) * g.uniform(0.99, 1.01, (H, W))
    valid = g.random((H, W)) < 0.8
    rng = np.where(valid, rng, g.choice([np.inf, np.nan, 0.0], (H, W)))
    inten = np.where(valid, g.uniform(0.0, 100.0, (H, W)), np.nan)
    owner = np.where(valid, g.integers(-1, 4, (H, W)), -1)
    return Sweep(rng.astype(np.float32), valid, inten.astype(np.float32), owner.astype(np.int64))


def assert_same(got: np.ndarray, ref: np.ndarray) -> None:
    """Equal dtype, shape and bytes (bit for bit, NaN included)."""
    assert got.dtype == ref.dtype and got.shape == ref.shape
    assert got.tobytes() == ref.tobytes(), f"{np.count_nonzero(got != ref)} elements differ"


# ------------------------------------------------------------------------ range edges


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_range_edges_match_the_numpy_reference_on_sweeps(seed: int, dtype: type) -> None:
    s = sweep(seed)
    rng = s.range_m.astype(dtype)
    for jump_m, frac in ((0.5, 0.05), (0.2, 0.01), (0.0, 0.0), (2.0, 0.2)):
        got = range_jump_edges(rng, s.valid, jump_m, frac)
        ref = range_jump_edges_reference(rng, s.valid, jump_m, frac)
        assert_same(got, ref)
        assert ref.any() and not ref.all()
    cfg = SegmentConfig()
    edge = range_edges(rng, s.valid, cfg)
    assert_same(edge, range_jump_edges_reference(rng, s.valid, cfg.edge_jump_m, cfg.edge_jump_frac))
    assert not edge[~s.valid].any()


@pytest.mark.parametrize(("H", "W"), SMALL)
@pytest.mark.parametrize("seed", range(3))
def test_range_edges_match_the_numpy_reference_on_small_images(seed: int, H: int, W: int) -> None:
    s = small_sweep(seed, H, W)
    for dtype, (jump_m, frac) in itertools.product(
        (np.float32, np.float64),
        # a negative threshold makes pixels jump against themselves at the bottom row and
        # in a one-column image: the reference's pairing of a pixel with itself, kept
        ((0.5, 0.05), (0.0, 0.0), (-1.0, 0.0), (0.1, -0.1)),
    ):
        rng = s.range_m.astype(dtype)
        odd = np.random.default_rng(seed).random((H, W))
        rng[s.valid & (odd < 0.1)] = -3.0
        rng[s.valid & (odd > 0.95)] = -np.inf
        assert_same(
            range_jump_edges(rng, s.valid, jump_m, frac),
            range_jump_edges_reference(rng, s.valid, jump_m, frac),
        )


def test_range_edges_of_degenerate_images() -> None:
    H, W = 8, 16
    flat = np.full((H, W), 10.0, np.float32)
    none = np.zeros((H, W), bool)
    assert not range_jump_edges(flat, none, 0.5, 0.05).any()
    assert not range_jump_edges(flat, ~none, 0.5, 0.05).any()
    # a valid NaN range makes no edge, nor does -inf (no finite nearer side); a valid +inf
    # is the far side of a jump for its four neighbours
    odd = flat.copy()
    odd[2, 3], odd[5, 9], odd[1, 12] = np.nan, np.inf, -np.inf
    got = range_jump_edges(odd, ~none, 0.5, 0.05)
    assert_same(got, range_jump_edges_reference(odd, ~none, 0.5, 0.05))
    assert got[5, 8] and got[4, 9] and got[5, 10] and got[6, 9] and got.sum() == 4
    # a step: the nearer side, along the row (wrapping round) and down the column
    step = flat.copy()
    step[:, W // 2 :] = 20.0
    got = range_jump_edges(step, ~none, 0.5, 0.05)
    assert set(np.flatnonzero(got.any(axis=0)).tolist()) == {W // 2 - 1, 0}
    down = flat.copy()
    down[H // 2 :, :] = 30.0
    got = range_jump_edges(down, ~none, 0.5, 0.05)
    assert np.flatnonzero(got.any(axis=1)).tolist() == [H // 2 - 1]
    # an empty pixel counts as infinitely far: the returns round it are the nearer side
    hole = ~none
    hole[3, 4] = False
    got = range_jump_edges(flat, hole, 0.5, 0.05)
    assert np.argwhere(got).tolist() == [[2, 4], [3, 3], [3, 5], [4, 4]]
    empty = np.zeros((0, 5), np.float32)
    assert range_jump_edges(empty, np.zeros((0, 5), bool), 0.5, 0.05).shape == (0, 5)


def test_range_edges_fall_back_to_the_reference_where_numpy_would_widen() -> None:
    s = sweep(9, 16, 128)
    # a float32 image with a numpy float64 threshold: numpy computes the threshold in
    # float64; an integer image; a valid mask of another dtype
    cases = [
        (s.range_m, s.valid, np.float64(0.5), 0.05),
        (np.nan_to_num(s.range_m, posinf=99).astype(np.int32), s.valid, 0.5, 0.05),
        (s.range_m, s.valid.astype(np.uint8), 0.5, 0.05),
    ]
    for rng, valid, jump_m, frac in cases:
        got = range_jump_edges(rng, valid, jump_m, frac)
        ref = range_jump_edges_reference(rng, valid, jump_m, frac)
        assert_same(got, ref)
    assert cases and range_jump_edges(*cases[0]).any()


# ------------------------------------------------------------------------ lists


def lists_inputs(s: Sweep, seed: int) -> tuple:
    """The arguments of list_slots_and_sums as sp.level2_lists.ListLevel.group builds them:
    range and brightness edges of the sweep, free-surface patches, and a table of the existing lists
    with some (owner, kind) keys still missing and one too large for it."""
    g = np.random.default_rng(seed)
    r_edge = range_edges(s.range_m, s.valid)
    b_edge = brightness_edges(s.intensity, s.valid) & ~r_edge
    H, W = s.owner.shape
    blocks = g.random((-(-H // 4), -(-W // 16))) < 0.3
    patch = np.kron(blocks, np.ones((4, 16), bool))[:H, :W] & s.valid
    n_keys = 4 * (int(s.owner.max(initial=0)) + 1)
    lut = np.full(n_keys - 3, -1, np.int64)
    have = g.permutation(lut.size)[: (3 * lut.size) // 4]
    lut[have] = np.arange(have.size)
    list_ids = 7 * np.arange(have.size, dtype=np.int64) + 1000
    return s.owner, r_edge, b_edge, patch, lut, list_ids


def check_lists(args: tuple, range_m: np.ndarray, intensity: np.ndarray) -> tuple:
    """The fused pass against the numpy slots and the per-pixel sums kernel, exactly;
    returns its (slots, ids, branches, missing, sums)."""
    r_edge, b_edge, list_ids = args[1], args[2], args[5]
    slots, ids, branches, missing, sums = list_slots_and_sums(*args, range_m, intensity)
    ref = list_slots_reference(*args)
    for got, want in zip((slots, ids, branches, missing), ref, strict=True):
        np.testing.assert_array_equal(got, want)
    assert branches.dtype == np.int8 and missing.dtype == np.int64
    for got, want in zip(list_slots(*args), ref, strict=True):
        np.testing.assert_array_equal(got, want)
    want = list_sums(slots, range_m, intensity, r_edge | b_edge, branches, list_ids.size)
    assert_same(sums, want)
    return slots, ids, branches, missing, sums


@pytest.mark.parametrize("seed", SEEDS)
def test_list_slots_and_sums_match_the_references_on_sweeps(seed: int) -> None:
    s = sweep(seed)
    args = lists_inputs(s, seed)
    slots, _, branches, missing, sums = check_lists(args, s.range_m, s.intensity)
    # every kind and every case was there: vertices, lists to sum, keys still missing
    assert ((branches == 1) | (branches >= 3)).any() and (branches == 2).any()
    assert sums[:, 0].sum() > 1000 and missing.size > 0 and (slots <= -2).any()
    # in float64 the numpy sums (bincounts) agree to rounding
    r64, i64 = s.range_m.astype(np.float64), s.intensity.astype(np.float64)
    slots64, _, branches64, _, sums64 = check_lists(args, r64, i64)
    edge = args[1] | args[2]
    ref = list_sums_reference(slots64, r64, i64, edge, branches64, args[5].size)
    np.testing.assert_allclose(sums64, ref, rtol=1e-12, atol=0.0)


@pytest.mark.parametrize(("H", "W"), SMALL)
@pytest.mark.parametrize("seed", range(3))
def test_list_slots_and_sums_match_the_references_on_small_images(
    seed: int, H: int, W: int
) -> None:
    s = small_sweep(seed, H, W)
    g = np.random.default_rng(seed)
    r_edge = g.random((H, W)) < 0.4
    b_edge = (g.random((H, W)) < 0.4) & ~r_edge
    patch = g.random((H, W)) < 0.5
    lut = np.array([0, -1, 1, 2, -1, 3, 4, 5, -1, 6], np.int64)  # owner 3's keys: missing
    list_ids = np.arange(7, dtype=np.int64) + 50
    # owners on the empty pixels too: their infinite and NaN ranges and intensities summed
    owner = g.integers(-1, 4, (H, W))
    for args in (
        (s.owner, r_edge, b_edge, patch, lut, list_ids),
        (owner, r_edge, b_edge, patch, lut, list_ids),
    ):
        check_lists(args, s.range_m, s.intensity)
        check_lists(args, s.range_m.astype(np.float64), s.intensity.astype(np.float64))


def test_list_slots_and_sums_of_degenerate_images() -> None:
    s = sweep(3, 16, 64)
    H, W = s.owner.shape
    args = lists_inputs(s, 3)
    owner, r_edge, b_edge, patch, lut, list_ids = args
    none = np.zeros((H, W), bool)
    # no edges and no patches: no lists, no sums
    slots, _, branches, missing, sums = check_lists(
        (owner, none, none, none, lut, list_ids), s.range_m, s.intensity
    )
    assert (slots == -1).all() and not branches.any() and missing.size == 0 and not sums.any()
    # every pixel an edge: none inside has a branch (its whole ring is on), the top row one
    every = ~none
    slots, _, branches, _, sums = check_lists(
        (owner, every, none, none, lut, list_ids), s.range_m, s.intensity
    )
    assert (branches[1:-1, 1:-1] == 0).all() and (branches[0, 1:-1] == 1).all()
    # no owners; no lists at all (empty tables); a table of one list for everything
    check_lists((np.full((H, W), -1), r_edge, b_edge, patch, lut, list_ids), s.range_m, s.intensity)
    empty = np.zeros(0, np.int64)
    _, _, _, missing, sums = check_lists(
        (owner, r_edge, b_edge, patch, empty, empty), s.range_m, s.intensity
    )
    assert sums.shape == (0, 12) and missing.size > 0
    one = np.zeros(4 * (int(owner.max()) + 1), np.int64)
    _, _, _, missing, sums = check_lists(
        (owner, r_edge, b_edge, patch, one, np.array([9], np.int64)), s.range_m, s.intensity
    )
    assert missing.size == 0 and sums[0, 0] == np.count_nonzero(
        (owner >= 0) & (r_edge | b_edge | patch)
    )
    # one pixel, and an all-NaN intensity
    px = (np.zeros((1, 1), np.int64), every[:1, :1], none[:1, :1], none[:1, :1], one, one[:1])
    check_lists(px, s.range_m[:1, :1], s.intensity[:1, :1])
    check_lists(args, s.range_m, np.full((H, W), np.nan, np.float32))
