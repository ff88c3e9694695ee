"""The compiled level-4 grouping (sp.segments.label_objects) against its numpy and scipy
reference (label_objects_reference): the same labels, exactly, on ray-cast scenes with every
rule's code path in use, on a simulated sweep as the pipeline builds it, on degenerate
images, and on links built to fall between the float32 and the float64 form of a threshold.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from sp.segments import SegmentConfig, label_objects, label_objects_reference

SENSOR_H = 1.8

# every rule that has its own code path on and off: the row gap (links across empty rows),
# the range step, the near join of small far pieces; min_pixels drops speckle or not
CONFIGS = [
    SegmentConfig(row_gap=g, step_m=s, near_pixels=n, min_pixels=k)
    for g, s, n, k in itertools.product((0, 2), (0.0, 0.2), (0, 10), (1, 4))
] + [
    # no range scaling along rows (r * 0, NaN for an infinite range), near join from 0 m
    SegmentConfig(join_per_rad=0.0, near_min_range_m=0.0, min_pixels=1),
    SegmentConfig(row_gap=5, step_m=0.05, step_frac=0.0, near_m=1.0, near_pixels=30),
]


def scene(seed: int, H: int, W: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """A ray-cast LADAR image: ground plane, walls, cars, poles, far thin objects (boxes),
    dropped returns and rows that do not fire (a sparse beam pattern binned by elevation).

    Returns xyz (H, W, 3) float64 (0 where empty), range (H, W) float64 (NaN, inf, 0 or -1
    where empty: every form of "no return"), valid (H, W) bool, row_step, col_step (rad).
    """
    g = np.random.default_rng(seed)
    el = np.linspace(np.radians(3.0), np.radians(-25.0), H)
    el = el + g.normal(0.0, 0.1, H) * (el[0] - el[1])  # rows not evenly spaced
    col_step = 2 * np.pi / W
    az = np.pi - (np.arange(W) + 0.5) * col_step + g.normal(0.0, 0.05 * col_step, W)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)
    boxes = []
    # a street: building fronts on four sides, with gaps, seen at grazing angles along it
    for axis, side in itertools.product((0, 1), (-1, 1)):
        at = side * g.uniform(6.0, 40.0)
        for lo, hi in zip(*(np.sort(g.uniform(-70, 70, (2, 3)), axis=0)), strict=True):
            c, half = np.zeros(2), np.zeros(2)
            c[axis], half[axis] = at, g.uniform(0.2, 1.0)
            c[1 - axis], half[1 - axis] = 0.5 * (lo + hi), 0.5 * (hi - lo)
            boxes.append((c - half, c + half, g.uniform(3.0, 15.0)))
            for _ in range(g.integers(0, 4)):  # people a step before the front (range steps)
                p = c.copy()
                p[axis] -= side * g.uniform(1.0, 3.0)
                p[1 - axis] = g.uniform(lo, hi)
                boxes.append((p - 0.25, p + 0.25, g.uniform(1.0, 2.0)))
    for _ in range(g.integers(8, 20)):  # cars and people, near and far
        c = g.uniform(-25, 25, 2)
        half = g.uniform(0.2, 2.5, 2)
        boxes.append((c - half, c + half, g.uniform(0.8, 2.0)))
    for _ in range(g.integers(10, 25)):  # poles and thin far objects: small far pieces
        ang, r = g.uniform(-np.pi, np.pi), g.uniform(15.0, 60.0)
        c = r * np.array([np.cos(ang), np.sin(ang)])
        half = g.uniform(0.03, 0.3, 2)
        boxes.append((c - half, c + half, g.uniform(1.0, 4.0)))
    for _ in range(g.integers(2, 6)):  # fences / bicycles: slats a little apart, far off
        ang, r = g.uniform(-np.pi, np.pi), g.uniform(16.0, 30.0)
        c, along = r * np.array([np.cos(ang), np.sin(ang)]), np.array([-np.sin(ang), np.cos(ang)])
        gap, top = g.uniform(0.3, 0.38), g.uniform(0.6, 1.2)
        for k in range(g.integers(3, 7)):
            p = c + k * gap * along
            boxes.append((p - 0.04, p + 0.04, top))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[..., 2] < -1e-6, -SENSOR_H / d[..., 2], np.inf)  # the ground
        for lo, hi, top in boxes:
            lo3 = np.array([lo[0], lo[1], -SENSOR_H])
            hi3 = np.array([hi[0], hi[1], top - SENSOR_H])
            t0, t1 = lo3 / d, hi3 / d
            tmin = np.nanmax(np.minimum(t0, t1), axis=-1)
            tmax = np.nanmin(np.maximum(t0, t1), axis=-1)
            t = np.where((tmax >= tmin) & (tmin > 0) & (tmin < t), tmin, t)
    t = np.where(t < 80.0, t + g.normal(0.0, 0.02, t.shape), np.inf)  # range noise
    t[g.random(H) < 0.3] = np.inf  # rows that do not fire
    t[g.random((H, W)) < 0.05] = np.inf  # dropped returns
    valid = np.isfinite(t) & (t >= 1.0)
    xyz = np.where(valid[..., None], d * np.where(valid, t, 0.0)[..., None], 0.0)
    empty_as = g.choice(np.array([np.nan, np.inf, 0.0, -1.0]), size=(H, W))
    rng = np.where(valid, t, empty_as)
    return xyz, rng, valid, float(el[0] - el[1]), col_step


def non_ground(xyz: np.ndarray, valid: np.ndarray, seed: int) -> np.ndarray:
    """The pipeline's grouping mask, roughly: valid returns above the ground, a few left out
    (a pixel that is valid but not grouped breaks image contiguity: the near join's case)."""
    keep = np.random.default_rng(seed + 1000).random(valid.shape) > 0.05
    return valid & (xyz[..., 2] > -SENSOR_H + 0.15) & keep


def assert_same(xyz, rng, mask, row_step, col_step, cfg: SegmentConfig) -> np.ndarray:
    got = label_objects(xyz, rng, mask, row_step, col_step, cfg)
    with np.errstate(invalid="ignore"):  # the reference's inf * 0 when join_per_rad is 0
        want = label_objects_reference(xyz, rng, mask, row_step, col_step, cfg)
    assert got.dtype == want.dtype == np.int64 and got.shape == want.shape
    bad = np.flatnonzero(got.reshape(-1) != want.reshape(-1))
    assert bad.size == 0, f"{bad.size} pixels differ under {cfg}, first at flat index {bad[:5]}"
    return want


@pytest.mark.parametrize("H, W", [(16, 64), (16, 1024), (64, 64), (64, 1024)])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(
    "xyz_dtype, rng_dtype, step_type",
    [
        (np.float64, np.float32, float),  # the pipeline's: float32 ranges, Python float steps
        (np.float64, np.float32, np.float64),  # numpy scalar steps: float64 limits
        (np.float64, np.float64, float),
        (np.float32, np.float32, float),
    ],
)
def test_kernel_gives_the_reference_labels(H, W, seed, xyz_dtype, rng_dtype, step_type):
    xyz, rng, valid, row_step, col_step = scene(seed, H, W)
    mask = non_ground(xyz, valid, seed)
    assert mask.sum() > 0.05 * H * W  # a scene, not an empty image
    xyz, rng = xyz.astype(xyz_dtype), rng.astype(rng_dtype)
    n_labels = set()
    for cfg in CONFIGS:
        want = assert_same(xyz, rng, mask, step_type(row_step), step_type(col_step), cfg)
        n_labels.add(int(want.max()) + 1)
    assert len(n_labels) > 1  # the configurations group the scene differently


@pytest.mark.parametrize("seed", [3, 4])
def test_kernel_gives_the_reference_labels_on_any_mask(seed):
    """A mask that is not a subset of the returns: links to pixels without a range (NaN, inf,
    0, -1; xyz 0) take numpy's NaN rules (np.minimum / np.maximum propagate NaN)."""
    xyz, rng, valid, row_step, col_step = scene(seed, 64, 1024)
    mask = np.random.default_rng(seed).random(valid.shape) < np.where(valid, 0.8, 0.3)
    assert (mask & ~valid).sum() > 1000
    for cfg in CONFIGS:
        assert_same(xyz, rng, mask, row_step, col_step, cfg)
        assert_same(xyz, rng.astype(np.float32), mask, row_step, col_step, cfg)


def test_scenes_exercise_every_rule():
    """The equality above means something only if each rule changes the labels somewhere."""
    changed = {"row_gap": 0, "step_m": 0, "near_pixels": 0, "min_pixels": 0}
    off = {"row_gap": 0, "step_m": 0.0, "near_pixels": 0, "min_pixels": 1}
    base = SegmentConfig(min_pixels=4)
    for seed, (H, W) in itertools.product(range(3), [(16, 1024), (64, 1024)]):
        xyz, rng, valid, row_step, col_step = scene(seed, H, W)
        mask = non_ground(xyz, valid, seed)
        ref = label_objects_reference(xyz, rng, mask, row_step, col_step, base)
        for name, value in off.items():
            cfg = dataclasses.replace(base, **{name: value})
            other = label_objects_reference(xyz, rng, mask, row_step, col_step, cfg)
            changed[name] += int(not np.array_equal(ref, other))
    assert all(n > 0 for n in changed.values()), changed


@pytest.fixture(scope="module")
def sweep():
    """A simulated sweep as the pipeline groups it: float64 points, float32 ranges (inf where
    empty), a non-ground mask, Python float angular steps."""
    from fixtures.simulate import simulate
    from logs.types import LadarScan
    from sp.egosphere import EgosphereConfig, to_egosphere

    scan = next(f for f in simulate("default", seconds=0.25) if isinstance(f, LadarScan))
    img = to_egosphere(scan, EgosphereConfig(n_rows=64, n_cols=1024, max_returns=1))
    valid = img.valid_first
    xyz = np.where(valid[..., None], img.xyz[..., 0, :], 0.0).astype(np.float64)
    rng = np.where(valid, img.range_first, np.inf)
    return xyz, rng, valid & (xyz[..., 2] > -1.5)


def test_kernel_gives_the_reference_labels_on_a_simulated_sweep(sweep):
    xyz, rng, mask = sweep
    assert rng.dtype == np.float32 and mask.sum() > 500
    for cfg in [SegmentConfig(min_pixels=1), SegmentConfig(), *CONFIGS]:
        want = assert_same(xyz, rng, mask, math.radians(1.0), 2 * math.pi / 1024, cfg)
        assert want.max() >= 10  # objects were found


@pytest.mark.parametrize("H, W", [(1, 1), (1, 2), (2, 1), (3, 2), (16, 64)])
@pytest.mark.parametrize("fill", ["none", "all", "all_no_range"])
def test_degenerate_images(H, W, fill):
    """No mask pixel, every pixel in the mask, and every pixel in the mask with no range; tiny
    images where the wrap links a pixel to itself or to its neighbour twice."""
    xyz, rng, _, row_step, _ = scene(7, 64, 64)
    xyz, rng = xyz[:H, :W].copy(), rng[:H, :W].copy()
    if fill == "all_no_range":
        rng[:] = np.nan
        xyz[:] = 0.0
    mask = np.full((H, W), fill != "none")
    for cfg in CONFIGS:
        want = assert_same(xyz, rng, mask, row_step, 2 * np.pi / W, cfg)
        if fill == "none" or cfg.min_pixels > H * W:
            assert (want == -1).all()
        elif cfg.min_pixels == 1:
            assert (want >= 0).all()


def test_all_mask_pixels_on_a_full_image():
    """Every pixel of a 64 x 1024 scene in the mask (the ground too: one large component)."""
    xyz, rng, valid, row_step, col_step = scene(5, 64, 1024)
    mask = np.ones_like(valid)
    for cfg in CONFIGS[:4]:
        want = assert_same(xyz, rng, mask, row_step, col_step, cfg)
        assert want.max() >= 1


def test_other_dtypes_take_the_reference_path():
    """An integer mask and float16 ranges are not the kernel's: the reference answers."""
    xyz, rng, valid, row_step, col_step = scene(6, 16, 64)
    mask = non_ground(xyz, valid, 6)
    for m, r in [(mask.astype(np.uint8), rng), (mask, rng.astype(np.float16))]:
        got = label_objects(xyz, r, m, row_step, col_step, SegmentConfig(min_pixels=1))
        want = label_objects_reference(xyz, r, m, row_step, col_step, SegmentConfig(min_pixels=1))
        assert np.array_equal(got, want) and want.max() >= 1


# --- the dtypes of the reference's arithmetic, at the boundaries where they decide -------------
#
# numpy forms ``r * step`` and ``max(join_m, .)`` in float32 for float32 ranges and Python float
# steps, in float64 for numpy float64 steps, and the range-step prefilter in the range's dtype;
# links whose distance falls between the float32 and the float64 limit tell them apart (random
# scenes almost never hold one).

ONLY_LINKS = SegmentConfig(min_pixels=1, near_pixels=0)
LINKS = {  # (di, dj, H, W): the second pixel of the link, the image that holds it
    "next": (0, 1, 1, 8),
    "next_but_one": (0, 2, 1, 8),
    "row_below": (1, 0, 2, 4),
    "across_an_empty_row": (2, 0, 3, 4),
}


def link_image(di: int, dj: int, H: int, W: int, d: float, r: float):
    """Two mask pixels (0, 0) and (di, dj) with range ``r`` (float32) whose points lie ``d``
    apart; no other return."""
    xyz = np.zeros((H, W, 3))
    xyz[di, dj, 0] = d
    rng = np.full((H, W), np.nan, dtype=np.float32)
    rng[0, 0] = rng[di, dj] = r
    mask = np.isfinite(rng)
    return xyz, rng, mask


def joined(labels: np.ndarray, mask: np.ndarray) -> bool:
    """The mask pixels (all grouped: min_pixels 1) are one segment."""
    assert (labels[mask] >= 0).all() and (labels[~mask] == -1).all()
    return np.unique(labels[mask]).size == 1


@pytest.mark.parametrize("link", sorted(LINKS))
def test_distance_limit_in_the_references_dtype(link):
    di, dj, H, W = LINKS[link]
    row_step, col_step = math.radians(1.0), 2 * math.pi / 1024
    cfg = ONLY_LINKS
    base = dj * col_step * cfg.join_per_rad if di == 0 else di * row_step * cfg.join_per_rad_row
    # a range at which the float32 and float64 products differ
    for r in np.float32(60.0) + np.arange(100, dtype=np.float32) * np.float32(0.01):
        lim32 = float(np.float32(r) * np.float32(base))
        lim64 = float(np.float64(r) * base)
        if lim32 != lim64:
            break
    else:
        pytest.fail("no range with differing products")
    outcome = {}
    for step_type in (float, np.float64):
        xyz, rng, mask = link_image(di, dj, H, W, 0.5 * (lim32 + lim64), r)
        steps = step_type(row_step), step_type(col_step)
        got = label_objects(xyz, rng, mask, *steps, cfg)
        assert np.array_equal(got, label_objects_reference(xyz, rng, mask, *steps, cfg))
        outcome[step_type] = joined(got, mask)
    # float32 limit for Python float steps, float64 for numpy ones: opposite answers
    assert outcome[float] == (lim32 > lim64) and outcome[np.float64] == (lim64 > lim32)


@pytest.mark.parametrize("link", sorted(LINKS))
def test_join_floor_in_the_references_dtype(link):
    """join_m (0.6) is float32 0.6000000238 against a float32 limit, 0.6 against a float64 one."""
    di, dj, H, W = LINKS[link]
    d = 0.5 * (0.6 + float(np.float32(0.6)))
    outcome = {}
    for step_type in (float, np.float64):
        xyz, rng, mask = link_image(di, dj, H, W, d, 2.0)
        steps = step_type(math.radians(1.0)), step_type(2 * math.pi / 1024)
        got = label_objects(xyz, rng, mask, *steps, ONLY_LINKS)
        assert np.array_equal(got, label_objects_reference(xyz, rng, mask, *steps, ONLY_LINKS))
        outcome[step_type] = joined(got, mask)
    assert outcome == {float: True, np.float64: False}


def test_range_step_prefilter_in_the_ranges_dtype():
    """A step just over the float64 threshold (so the float64 rule cuts it) but not over the
    float32 one: with float32 ranges the prefilter keeps the link, with float64 it is cut."""
    cfg = ONLY_LINKS
    ra = np.linspace(0.01, 0.05, 200_001).astype(np.float32)
    thr32 = cfg.step_m + cfg.step_frac * ra  # the reference's expression on float32 ranges
    thr64 = cfg.step_m + cfg.step_frac * ra.astype(np.float64)
    rb = (ra + thr64).astype(np.float32)
    hit = (np.abs(rb - ra) <= thr32) & (rb.astype(np.float64) - ra.astype(np.float64) > thr64)
    assert hit.any()
    k = int(np.flatnonzero(hit)[0])
    # p, a | b, q along a row: flat on both sides of the step, the link a - b 0.1 m long
    rng = np.array([[ra[k], ra[k], rb[k], rb[k], np.nan, np.nan]], dtype=np.float32)
    xyz = np.zeros((1, 6, 3))
    xyz[0, 2, 0] = 0.1
    mask = np.array([[False, True, True, False, False, False]])
    outcome = {}
    for dtype in (np.float32, np.float64):
        r = rng.astype(dtype)
        got = label_objects(xyz, r, mask, math.radians(1.0), 2 * math.pi / 6, cfg)
        want = label_objects_reference(xyz, r, mask, math.radians(1.0), 2 * math.pi / 6, cfg)
        assert np.array_equal(got, want)
        outcome[dtype] = joined(got, mask)
    assert outcome == {np.float32: True, np.float64: False}
