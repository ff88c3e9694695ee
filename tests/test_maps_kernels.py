"""The compiled fusion and ray-casting kernels (maps.kernels) against their references: the
numpy fusion path (``FusionConfig(compiled=False)``) on random, NaN/inf-laden, out-of-window,
single-point and empty sweeps, for one level and for the stack; ray casting against a plain
Python segment-square reference and a hand-built scene with known free and occupied cells."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from maps.fusion import FusionConfig, FusionError, cast_rays, fuse_points
from maps.level import LevelConfig, MapLevel
from maps.stack import MapStack, StackConfig, StackError

KERNEL = FusionConfig()
NUMPY = FusionConfig(compiled=False)
EXACT = {"count", "obstacle_count", "last_seen_ns", "occupancy", "elevation_min", "elevation_max"}


def assert_same_layers(a: MapLevel, b: MapLevel) -> None:
    """Discrete layers and min / max equal; estimates equal up to the rounding of the sums'
    centring height (the kernel's sequential mean against numpy's pairwise one)."""
    for name in a.layer_names:
        x, y = a.storage(name), b.storage(name)
        if name in EXACT:
            np.testing.assert_array_equal(x, y, err_msg=name)
        elif x.dtype == np.float32:
            np.testing.assert_allclose(x, y, rtol=2e-6, atol=1e-6, err_msg=name)
        else:
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9, err_msg=name)


def random_sweep(rng: np.random.Generator, n: int, bad: float = 0.05) -> np.ndarray:
    """Points over an 8 x 8 m patch (partly outside a 16 x 0.5 m window), a slope, obstacle
    points, a table top, and a share ``bad`` of NaN/inf coordinates."""
    xy = rng.uniform([-3.0, -6.0], [7.0, 4.0], size=(n, 2))
    z = 0.3 * xy[:, 0] + rng.normal(0, 0.05, n)
    z[rng.random(n) < 0.1] += rng.uniform(0.5, 2.0)
    top = (xy[:, 0] >= 2.5) & (xy[:, 1] >= -0.5) & (xy[:, 1] < 1.0)
    z[top & (rng.random(n) < 0.5)] += 1.0
    pts = np.column_stack([xy, z])
    hit = rng.random(n) < bad
    pts[hit, rng.integers(0, 3, int(hit.sum()))] = rng.choice([np.nan, np.inf, -np.inf])
    return pts


def fuse_both(levels: list[MapLevel], batches: list) -> None:
    for t_ns, pts, var in batches:
        sa = fuse_points(levels[0], pts, var, t_ns=t_ns, config=KERNEL)
        sb = fuse_points(levels[1], pts, var, t_ns=t_ns, config=NUMPY)
        assert sa == sb


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_batches=st.integers(1, 4), bad=st.sampled_from([0, 0.3]))
def test_kernel_fusion_equals_numpy_fusion(seed: int, n_batches: int, bad: float) -> None:
    rng = np.random.default_rng(seed)
    levels = [MapLevel(LevelConfig("t", 0.5, 16)) for _ in range(2)]
    for lvl in levels:
        lvl.move_to(np.array([2.0, -1.0]))
    batches = []
    for b in range(n_batches):
        n = int(rng.integers(1, 400))
        pts = random_sweep(rng, n, bad)
        var = rng.uniform(1e-4, 1e-2, n) if b % 2 == 0 else 3e-3  # per point, then scalar
        if b == 2:
            var[rng.random(n) < 0.1] = rng.choice([0.0, -1.0, np.nan])  # refused variances
        batches.append((100 + b, pts, var))
    fuse_both(levels, batches)
    assert_same_layers(*levels)


@pytest.mark.filterwarnings("ignore:invalid value encountered in cast")  # numpy, 1e300 / res
def test_kernel_fusion_edge_cases_equal_numpy() -> None:
    """Empty, single-point, all outside, all NaN/inf, points on cell edges, a non-power-of-two
    window, and float32 / Fortran-ordered input."""
    rng = np.random.default_rng(5)
    for size in (16, 12):
        levels = [MapLevel(LevelConfig("t", 0.5, size)) for _ in range(2)]
        edges = np.column_stack([np.arange(-4, 4) * 0.5, np.arange(-4, 4) * -0.5, np.zeros(8)])
        batches = [
            (1, np.zeros((0, 3)), 1e-3),
            (2, np.array([[0.3, -0.2, 1.0]]), 1e-3),
            (3, np.array([[0.3, -0.2, 0.0]]), np.array([1e-3])),
            (4, np.array([[500.0, 0.0, 0.0], [0.0, -1e300, 0.0]]), 1e-3),
            (5, np.full((5, 3), np.nan), 1e-3),
            (6, edges, 1e-3),
            (7, np.asfortranarray(random_sweep(rng, 500)).astype(np.float32), 2e-3),
        ]
        fuse_both(levels, batches)
        assert_same_layers(*levels)
        assert levels[0].window("count").sum() > 0


def test_stack_kernel_equals_numpy_stack_and_counts_each_point_once_per_level() -> None:
    rng = np.random.default_rng(21)
    levels = (
        LevelConfig("a", 0.1, 32, keep_tiles=False),
        LevelConfig("b", 0.5, 32, keep_tiles=False),
        LevelConfig("c", 2.5, 32, keep_tiles=False),
    )
    fusions = [replace(f, ray_free_height_m=3.0) for f in (KERNEL, NUMPY)]
    stacks = [MapStack(StackConfig(levels, f, raycast_levels=("b", "c"))) for f in fusions]
    sensor = np.array([0.0, 0.0, 2.0])
    for t, centre in enumerate(([0.3, 0.2], [1.7, -0.9], [4.0, 2.2], [4.1, 2.2])):
        xy = np.array(centre) + rng.normal(0, 12.0, size=(20000 if t < 3 else 1500, 2))
        z = 0.05 * xy[:, 0] + rng.normal(0, 0.02, len(xy))
        z[rng.random(len(xy)) < 0.05] += 1.5
        pts = np.column_stack([xy, z])
        pts[rng.random(len(xy)) < 0.01, 2] = np.nan
        kw = {"variance_m2": rng.uniform(1e-4, 4e-4, len(xy))} if t < 2 else {"sensor_xyz": sensor}
        if t == 3:
            kw["ray_origin_xyz"] = sensor + np.array([*centre, 0.0])
        got = []
        for stack in stacks:
            stack.move_to(np.array(centre))
            got.append(stack.fuse(pts, t_ns=t, **kw))
        assert got[0] == got[1]
        assert t < 3 or got[0].cells_freed["b"] > 20
        for lvl in stacks[0].levels:  # every level counts each point of its window once
            inside = lvl.contains(pts) & np.isfinite(pts).all(axis=1)
            assert got[0].ground[lvl.name] + got[0].obstacle[lvl.name] == int(inside.sum())
    for mine, ref in zip(stacks[0].levels, stacks[1].levels, strict=True):
        assert_same_layers(mine, ref)


def test_kernel_points_refuse_bad_shapes() -> None:
    level = MapLevel(LevelConfig("t", 0.5, 16))
    with pytest.raises(FusionError, match=r"\(N, 3\).*\(4, 2\)"):
        fuse_points(level, np.zeros((4, 2)), 1e-3, t_ns=0)
    with pytest.raises(FusionError, match=r"\(4,\), got shape \(3,\)"):
        fuse_points(level, np.zeros((4, 3)), np.ones(3), t_ns=0)
    with pytest.raises(FusionError, match="variance_m2 or sensor_xyz"):
        MapStack().fuse(np.zeros((3, 3)), t_ns=0)
    with pytest.raises(FusionError, match="ray_origin_xyz"):
        fuse_points(level, np.zeros((4, 3)), 1e-3, t_ns=0, ray_origin_xyz=[0.0, np.nan, 1.0])
    with pytest.raises(StackError, match=r"raycast_levels \['subsystem'\]"):
        stack = MapStack(StackConfig(levels=(LevelConfig("a", 1.0, 8),)))
        stack.fuse(np.zeros((3, 3)), t_ns=0, variance_m2=1e-3, ray_origin_xyz=np.zeros(3))


# --- ray casting ---------------------------------------------------------------------------


def _segment_cells(p: np.ndarray, s: np.ndarray, res: float):
    """Cells (ix, iy) whose square the 2-D segment from ``s`` to ``p`` (metres) crosses, with
    the parameter interval (from ``s``) of the crossing (Liang-Barsky clipping per cell)."""
    lo = np.floor(np.minimum(p, s) / res).astype(int)
    hi = np.floor(np.maximum(p, s) / res).astype(int)
    d = p - s
    for ix in range(lo[0], hi[0] + 1):
        for iy in range(lo[1], hi[1] + 1):
            u0, u1 = 0.0, 1.0
            for k, (a, b) in enumerate(((ix * res, (ix + 1) * res), (iy * res, (iy + 1) * res))):
                if d[k] == 0:
                    if not a <= s[k] < b:
                        u0, u1 = 1.0, 0.0
                    continue
                ua, ub = sorted(((a - s[k]) / d[k], (b - s[k]) / d[k]))
                u0, u1 = max(u0, ua), min(u1, ub)
            if u1 > u0:
                yield ix, iy, u0, u1


def _reference_rays(level, pts, origin, touched, cfg: FusionConfig) -> set:
    """Cells lowered by the rule of :func:`maps.kernels.cast_rays`, by plain geometry."""
    res = level.resolution_m
    horiz = np.linalg.norm(pts[:, :2] - origin[:2], axis=1)
    t_lim = np.minimum(1.0, cfg.ray_max_range_m / horiz)
    start = origin + t_lim[:, None] * (pts - origin)
    keys = [tuple(k) for k in np.floor(start[:, :2] / res).astype(int)]
    chosen: dict = {}
    for i, key in enumerate(keys):  # the lowest beam per start cell
        if key not in chosen or pts[i, 2] < pts[chosen[key], 2]:
            chosen[key] = i
    elev = {}
    lowered: set = set()
    for i in chosen.values():
        end = tuple(np.floor(pts[i, :2] / res).astype(int))
        for ix, iy, u0, u1 in _segment_cells(origin[:2], start[i, :2], res):
            if (ix, iy) == end or (ix, iy) in touched or (ix, iy) in lowered:
                continue
            if not level.contains(np.array([[ix + 0.5, iy + 0.5]]) * res)[0]:
                continue
            z = origin[2] + (pts[i, 2] - origin[2]) * t_lim[i] * (1 - 0.5 * (u0 + u1))
            if (ix, iy) not in elev:
                centre = np.array([[ix + 0.5, iy + 0.5]]) * res
                elev[ix, iy] = [level.read(n, centre)[0] for n in ("elevation", "elevation_max")]
            ground, top = elev[ix, iy]
            ground = pts[i, 2] if np.isnan(ground) else ground
            if z - ground <= cfg.ray_free_height_m and not z > top:
                lowered.add((ix, iy))
    return lowered


def test_ray_kernel_equals_segment_reference() -> None:
    rng = np.random.default_rng(3)
    cfg = FusionConfig(ray_max_range_m=6.0, ray_free_height_m=0.8, ray_stop_after_cells=0)
    level = MapLevel(LevelConfig("t", 0.5, 32))
    origin = np.array([0.3, -0.2, 1.2])
    ground = np.column_stack([rng.uniform(-7, 7, (300, 2)), rng.normal(0.0, 0.02, 300)])
    fuse_points(level, ground, 1e-4, t_ns=0, config=cfg)  # some cells know their ground
    az = rng.uniform(-np.pi, np.pi, 400)
    r = rng.uniform(0.5, 10.0, 400)
    pts = np.column_stack([r * np.cos(az), r * np.sin(az), rng.uniform(-0.2, 2.5, 400)])
    pts += origin * [1, 1, 0]
    fuse_points(level, pts, 1e-3, t_ns=1, config=cfg)
    after_points = level.storage("occupancy").copy()
    touched = {tuple(k) for k in level.world_to_cell(pts)}
    lowered = cast_rays(level, pts, origin, cfg)
    ref = _reference_rays(level, pts, origin, touched, cfg)
    srow, scol = np.nonzero(level.storage("occupancy") != after_points)
    ox, oy, size = *level.origin_cell, level.size
    ix, iy = (ox + (scol - ox) % size).tolist(), (oy + (srow - oy) % size).tolist()
    got = set(zip(ix, iy, strict=True))
    assert lowered == len(got) > 20
    assert got == ref


@pytest.mark.parametrize("stride", [1, 4])
def test_rays_free_the_cells_before_a_wall_and_leave_those_behind(stride: int) -> None:
    """A wall of returns 10 m ahead (no ground seen; the height rule off: plain 2-D
    traversal): the cells between the sensor and the wall end free (negative log-odds), the
    wall cells occupied, the cells behind it and beside the beam fan untouched."""
    cfg = FusionConfig(ray_free_height_m=100.0, ray_stride=stride)
    level = MapLevel(LevelConfig("t", 0.4, 128))
    sensor = np.array([0.2, 0.2, 1.5])
    y, z = np.meshgrid(np.linspace(-3.0, 3.0, 121), np.linspace(0.1, 2.0, 20))
    wall = np.column_stack([np.full(y.size, 10.1), y.ravel() + 0.2, z.ravel()])
    for t in range(3):
        stats = fuse_points(level, wall, 1e-3, t_ns=t, config=cfg, ray_origin_xyz=sensor)
    assert stats.cells_freed["t"] > 100
    occ = level.window("occupancy")
    cx = (np.arange(128) + level.origin_cell[0] + 0.5) * 0.4  # window column centres, x
    cy = (np.arange(128) + level.origin_cell[1] + 0.5) * 0.4
    X, Y = np.meshgrid(cx, cy)  # [row, col] like the window
    in_fan = np.abs(Y - 0.2) < 0.25 * (X - 0.2)  # well inside the fan of beams (|y| < 3 m at x=10)
    between = in_fan & (X > 0.6) & (X < 9.6)
    free = np.isclose(occ[between], 3 * cfg.l_miss)
    assert free.mean() == 1.0 if stride == 1 else free.mean() > 0.95  # beams left out: gaps
    wall_cells = (np.abs(X - 10.2) < 0.2) & (np.abs(Y - 0.2) < 2.8)
    assert np.all(occ[wall_cells] > 0)
    behind = X > 10.6
    assert np.all(occ[behind] == 0)
    aside = np.abs(Y - 0.2) > 0.35 * (X - 0.2) + 0.8  # clearly outside the fan
    assert np.all(occ[aside] == 0)


def test_rays_do_not_free_cells_they_pass_high_above() -> None:
    """A beam to a far low point crosses the near cells (their ground known at 0 m, a priori)
    higher than ``ray_free_height_m``: they stay unknown; the cells near its end, where it is
    low, free."""
    cfg = FusionConfig(ray_free_height_m=1.0)
    level = MapLevel(LevelConfig("t", 0.5, 64))
    level.set_window("elevation", np.zeros((64, 64), dtype=np.float32))
    sensor = np.array([0.1, 0.1, 3.0])  # 3 m up: a beam to (10, 0.1, 0.5) is low only near it
    fuse_points(level, np.array([[10.1, 0.1, 0.5]]), 1e-4, t_ns=1, config=cfg,
                ray_origin_xyz=sensor)  # fmt: skip
    rows, cols = np.nonzero(level.window("occupancy") < 0)
    xy = level.window_to_world(rows, cols)
    # beam height above ground at x: 3 - 2.5 x / 10 <= 1 m  ->  x >= 8 m
    assert len(xy) > 0 and xy[:, 0].min() >= 7.5 and xy[:, 0].max() < 10.0
    assert np.all(np.abs(xy[:, 1] - 0.1) < 0.5)


def test_rays_pass_over_an_object_top_but_clear_a_cell_it_has_left() -> None:
    """Cells with a 1 m high top seen in them: a beam over the top leaves them, a beam below
    it (the object has gone) frees them."""
    cfg = FusionConfig(ray_free_height_m=2.0)
    level = MapLevel(LevelConfig("t", 0.5, 64))
    top = np.column_stack([np.full(5, 5.25), np.full(5, 0.25), np.linspace(0.2, 1.0, 5)])
    fuse_points(level, top, 1e-4, t_ns=0, config=cfg)  # max 1.0 m in cell (10, 0)
    cell = np.array([[5.25, 0.25]])
    occ0 = level.read("occupancy", cell)[0]
    far = np.array([[10.25, 0.25, 1.6]])
    fuse_points(level, far, 1e-4, t_ns=1, config=cfg, ray_origin_xyz=[0.25, 0.25, 1.6])
    assert level.read("occupancy", cell)[0] == occ0  # crossed at 1.6 m, over the 1 m top
    assert level.read("occupancy", np.array([[3.25, 0.25]]))[0] < 0  # no point there: freed
    low = np.array([[10.25, 0.25, 0.6]])
    fuse_points(level, low, 1e-4, t_ns=2, config=cfg, ray_origin_xyz=[0.25, 0.25, 0.6])
    assert level.read("occupancy", cell)[0] == pytest.approx(occ0 + cfg.l_miss)


def test_ray_max_beams_traces_every_kth_beam_of_a_dense_sweep() -> None:
    """With ``ray_max_beams`` a sweep of N beams is traced at stride ceil(N / cap): the same
    cells as that stride given explicitly, fewer than all beams would free; a sweep within the
    cap is traced whole; a cap below 1 is refused by name."""
    y, z = np.meshgrid(np.linspace(-3.0, 3.0, 121), np.linspace(0.1, 2.0, 20))
    wall = np.column_stack([np.full(y.size, 10.1), y.ravel() + 0.2, z.ravel()])  # 2420 beams
    sensor = np.array([0.2, 0.2, 1.5])

    def occupancy(**cfg) -> np.ndarray:
        level = MapLevel(LevelConfig("t", 0.4, 128))
        config = FusionConfig(ray_free_height_m=100.0, **cfg)
        fuse_points(level, wall, 1e-3, t_ns=0, config=config, ray_origin_xyz=sensor)
        return level.window("occupancy")

    capped = occupancy(ray_max_beams=len(wall) // 4 + 1)  # stride 4
    assert np.array_equal(capped, occupancy(ray_stride=4, ray_max_beams=None))
    full = occupancy(ray_max_beams=None)
    assert (capped < 0).sum() < (full < 0).sum()
    assert np.array_equal(occupancy(ray_max_beams=len(wall)), full)
    with pytest.raises(FusionError, match="ray_max_beams must be >= 1"):
        occupancy(ray_max_beams=0)
