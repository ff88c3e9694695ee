"""Point fusion against a slow point-by-point reference, a known height function, and the
stack's level chain against direct fusion; what ray casting frees and leaves (the compiled
fusion and cast against their references are in the kernel harness,
test_kernel_equivalence.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from maps.fusion import (
    FusionConfig,
    FusionError,
    fuse_labels,
    fuse_points,
    labels_from_entity_image,
    range_variance,
)
from maps.level import LevelConfig, MapLevel
from maps.stack import MapStack, StackConfig


def _reference(batches, res: float, cfg: FusionConfig) -> dict:
    """Slow reference: a Python loop over points, one scalar Kalman update per point."""
    cells: dict = {}
    for t_ns, pts, var in batches:
        ok = np.isfinite(pts).all(axis=1)
        pts, var = pts[ok], var[ok]
        keys = [(int(np.floor(p[0] / res)), int(np.floor(p[1] / res))) for p in pts]
        lowest: dict = {}
        for k, p in zip(keys, pts, strict=True):
            lowest[k] = min(lowest.get(k, np.inf), p[2])
        start = {k: (c["x"], c["P"]) for k, c in cells.items()}
        for k in set(keys):  # a lowest point far below the estimate refutes it: start again
            x0, P0 = start.get(k, (np.nan, np.nan))
            if np.isfinite(x0) and lowest[k] < x0 - 3 * np.sqrt(P0) - cfg.obstacle_height_m:
                cells[k].update(x=np.nan, P=np.nan, n=0, W=0.0, mean=0.0, m2=0.0, stale=True)
        hits: dict = {}
        for k, p, v in zip(keys, pts, var, strict=True):
            c = cells.setdefault(
                k, dict(x=np.nan, P=np.nan, n=0, mean=0.0, m2=0.0, lo=np.inf, hi=-np.inf, nob=0)
            )
            c.update(lo=min(c["lo"], p[2]), hi=max(c["hi"], p[2]), seen=t_ns)
            x0, P0 = start.get(k, (np.nan, np.nan))
            if np.isfinite(x0) and not c.get("stale"):
                ref = x0 + 3 * np.sqrt(P0)
            else:
                ref = _new_ref(k, lowest, start, res, cfg)
            if p[2] > ref + cfg.obstacle_height_m:
                c["nob"] += 1
                hits[k] = True
                continue
            hits.setdefault(k, False)
            if np.isnan(c["x"]):
                c["x"], c["P"] = p[2], v
            else:
                K = c["P"] / (c["P"] + v)
                c["x"] += K * (p[2] - c["x"])
                c["P"] *= 1 - K
            c["n"] += 1
            c["W"] = c.get("W", 0.0) + 1.0 / v  # weighted Welford (West 1979)
            d = p[2] - c["mean"]
            c["mean"] += d / v / c["W"]
            c["m2"] += d * (p[2] - c["mean"]) / v
        for c in cells.values():
            c.pop("stale", None)
        for k, hit in hits.items():
            c = cells[k]
            c["occ"] = float(np.clip(c.get("occ", 0.0) + (cfg.l_hit if hit else cfg.l_miss), -4, 4))
    return cells


def _new_ref(k, lowest: dict, start: dict, res: float, cfg: FusionConfig) -> float:
    """Reference of a cell with no estimate: own lowest point, or a lower neighbour + slope."""
    nb = np.inf
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            n = (k[0] + dx, k[1] + dy)
            if n == k:
                continue
            x0 = start.get(n, (np.nan,))[0]
            nb = min(nb, x0 if np.isfinite(x0) else lowest.get(n, np.inf))
    return min(lowest[k], nb + cfg.max_ground_slope * np.sqrt(2) * res)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_batches=st.integers(1, 4))
def test_fusion_equals_slow_reference(seed: int, n_batches: int) -> None:
    rng = np.random.default_rng(seed)
    res, cfg = 0.5, FusionConfig()
    level = MapLevel(LevelConfig("t", res, 16))
    level.move_to(np.array([2.0, -1.0]))
    batches = []
    for b in range(n_batches):
        n = int(rng.integers(1, 300))
        xy = rng.uniform([0.0, -3.0], [4.0, 1.0], size=(n, 2))  # ~ 8 x 8 cells, many per cell
        z = 0.3 * xy[:, 0] + rng.normal(0, 0.05, n)
        z[rng.random(n) < 0.1] += rng.uniform(0.5, 2.0)  # some obstacle points
        if b == 0:  # a table top hides the ground of a 3 x 3 cell patch in the first sweep
            top = (xy[:, 0] >= 2.5) & (xy[:, 1] >= -0.5) & (xy[:, 1] < 1.0)
            z[top] += 1.0
        pts = np.column_stack([xy, z])
        pts[rng.random(n) < 0.05, rng.integers(0, 3)] = np.nan
        var = rng.uniform(1e-4, 1e-2, n)
        batches.append((1000 + b, pts, var))
        stats = fuse_points(level, pts, var, t_ns=1000 + b, config=cfg)
        assert stats.dropped_nonfinite == int((~np.isfinite(pts).all(axis=1)).sum())
    ref = _reference(batches, res, cfg)
    keys = np.array(list(ref), dtype=np.int64)
    xy = level.cell_to_world(keys)
    got = {name: level.read(name, xy) for name in level.layer_names}
    fields = ("x", "P", "n", "nob", "lo", "hi", "m2", "W", "occ", "seen")
    exp = {f: np.array([c.get(f, np.nan) for c in ref.values()]) for f in fields}
    np.testing.assert_allclose(got["elevation"], exp["x"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got["elevation_var"], exp["P"], rtol=1e-5)
    np.testing.assert_array_equal(got["count"], exp["n"])
    np.testing.assert_array_equal(got["obstacle_count"], exp["nob"])
    np.testing.assert_allclose(got["elevation_min"], exp["lo"], rtol=1e-6)
    np.testing.assert_allclose(got["elevation_max"], exp["hi"], rtol=1e-6)
    with np.errstate(invalid="ignore", divide="ignore"):  # np.where computes both branches
        rough = np.where(exp["n"] > 0, np.sqrt(np.maximum(exp["m2"], 0) / exp["W"]), np.nan)
    np.testing.assert_allclose(got["roughness"], rough, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(got["occupancy"], exp["occ"], rtol=1e-6)
    np.testing.assert_array_equal(got["last_seen_ns"], exp["seen"])


def _height(xy: np.ndarray) -> np.ndarray:
    """A known smooth terrain, metres."""
    return 0.4 * np.sin(0.15 * xy[:, 0]) + 0.03 * xy[:, 1] + 2.0


def test_fused_elevation_matches_a_known_height_function() -> None:
    rng = np.random.default_rng(7)
    cfg = FusionConfig()
    level = MapLevel(LevelConfig("t", 0.4, 128))
    level.move_to(np.array([0.0, 0.0]))
    sensor = np.array([0.0, 0.0, 3.5])
    for sweep in range(10):
        xy = rng.uniform(-25, 25, size=(20000, 2))
        r = np.linalg.norm(np.column_stack([xy, _height(xy)]) - sensor, axis=1)
        var = range_variance(r, cfg)
        z = _height(xy) + rng.normal(0, np.sqrt(var))
        fuse_points(level, np.column_stack([xy, z]), var, t_ns=sweep, config=cfg)
    rows, cols = np.nonzero(np.isfinite(level.window("elevation")))
    centres = level.window_to_world(rows, cols)
    est = level.window("elevation")[rows, cols]
    err = est - _height(centres)
    rmse = float(np.sqrt(np.mean(err**2)))
    assert rmse < 0.02, rmse  # ~13 points per cell with 2-5 cm noise each
    # the filter's variance is honest: normalised errors have about unit spread
    sd = np.sqrt(level.window("elevation_var")[rows, cols])
    assert 0.5 < float(np.std(err / sd)) < 3.0
    assert level.window("count")[rows, cols].sum() == 200000
    assert np.all(level.window("occupancy")[rows, cols] < 0)  # ground only


def test_an_estimate_refuted_by_lower_points_starts_again() -> None:
    """A patch first seen only on an object's top (nothing lower around) is taken for ground;
    when the object has gone and the ground shows 1 m below, the cells start again."""
    rng = np.random.default_rng(2)
    level = MapLevel(LevelConfig("t", 0.5, 32))
    xy = rng.uniform(-2, 2, size=(5000, 2))
    fuse_points(level, np.column_stack([xy, np.full(len(xy), 1.0)]), 1e-4, t_ns=1)
    assert np.nanmax(np.abs(level.window("elevation") - 1.0)) < 1e-6
    z = rng.normal(0.0, 0.01, len(xy))
    fuse_points(level, np.column_stack([xy, z]), 1e-4, t_ns=2)
    known = np.isfinite(level.window("elevation"))
    assert np.abs(level.window("elevation")[known]).max() < 0.05
    assert level.window("count").sum() == len(xy)  # the refuted sweep no longer counts


def test_obstacles_raise_occupancy_not_elevation() -> None:
    rng = np.random.default_rng(3)
    level = MapLevel(LevelConfig("t", 0.5, 32))
    xy = rng.uniform(-5, 5, size=(20000, 2))
    z = np.zeros(len(xy)) + rng.normal(0, 0.01, len(xy))
    box = (np.abs(xy[:, 0] - 2.0) < 1.0) & (np.abs(xy[:, 1]) < 1.0)
    fuse_points(level, np.column_stack([xy, z]), 1e-4, t_ns=1)  # ground first
    z_box = np.where(box, rng.uniform(0.0, 1.5, len(xy)), z)  # a box on the ground: walls
    fuse_points(level, np.column_stack([xy, z_box]), 1e-4, t_ns=2)
    occ = level.read("occupancy", np.array([[2.0 + 0.1, 0.1], [-2.0, 0.1]]))
    assert occ[0] > 0 > occ[1]
    elev = level.read("elevation", np.array([[2.1, 0.1]]))[0]
    assert abs(elev) < 0.05
    assert level.read("elevation_max", np.array([[2.1, 0.1]]))[0] > 1.0


def test_stack_chain_equals_direct_fusion_per_level() -> None:
    """Fine levels hand their sums to coarse ones: each coarse level must hold exactly what
    fusing all its points directly gives, with no point counted twice."""
    rng = np.random.default_rng(11)
    fcfg = FusionConfig(obstacle_height_m=1e3)
    levels = (
        LevelConfig("a", 0.1, 32, keep_tiles=False),
        LevelConfig("b", 0.5, 32, keep_tiles=False),
        LevelConfig("c", 2.5, 32, keep_tiles=False),
    )
    stack = MapStack(StackConfig(levels=levels, fusion=fcfg))
    direct = [MapLevel(c) for c in levels]
    for t, centre in enumerate(([0.3, 0.2], [1.7, -0.9], [4.0, 2.2])):
        stack.move_to(np.array(centre))
        for lvl in direct:
            lvl.move_to(np.array(centre))
        xy = np.array(centre) + rng.normal(0, 12.0, size=(30000, 2))
        z = _height(xy) + rng.normal(0, 0.02, len(xy))
        pts = np.column_stack([xy, z])
        var = rng.uniform(1e-4, 4e-4, len(xy))
        stats = stack.fuse(pts, variance_m2=var, t_ns=t)
        for lvl in direct:
            fuse_points(lvl, pts, var, t_ns=t, config=fcfg)
        for lvl in direct:  # every level counts each point of its window once
            assert stats.ground[lvl.name] == int(lvl.contains(pts).sum())
    for mine, ref in zip(stack.levels, direct, strict=True):
        for name in ("count", "elevation_min", "elevation_max", "last_seen_ns"):
            np.testing.assert_array_equal(mine.window(name), ref.window(name), err_msg=name)
        for name in ("elevation", "elevation_var", "roughness"):
            np.testing.assert_allclose(
                mine.window(name), ref.window(name), rtol=2e-5, atol=1e-6, err_msg=name
            )


def test_labels_arrive_from_an_entity_image_through_its_range() -> None:
    level = MapLevel(LevelConfig("t", 0.5, 32))
    ent = np.full((4, 5), -1, dtype=np.int64)
    ent[1:3, 1:4] = 42
    cls = np.where(ent >= 0, 7, -1)
    xyz = np.zeros((4, 5, 3))
    xyz[..., 0] = np.arange(5)[None, :] * 1.0 + 0.2  # pixels look at x = 0.2 .. 4.2 m
    xyz[..., 1] = np.arange(4)[:, None] * 1.0 + 0.2
    xyz[0, 0] = np.nan
    pts, ids, classes = labels_from_entity_image(ent, cls, xyz)
    assert len(pts) == 6
    assert fuse_labels(level, pts, ids, classes) == 6
    assert np.count_nonzero(level.window("entity_id") == 42) == 6
    got = level.read("class_id", np.array([[1.2, 1.2], [0.2, 1.2]]))
    assert got.tolist() == [7, -1]
    stack = MapStack()
    written = stack.fuse_labels(pts, ids, classes)
    assert written == {"primitive": 6, "subsystem": 6, "vehicle": 6, "section": 6}
    assert stack.level("vehicle").read("entity_id", pts[:1])[0] == 42


def test_bad_points_are_refused_or_counted() -> None:
    level = MapLevel(LevelConfig("t", 0.5, 16))
    with pytest.raises(FusionError, match=r"\(N, 3\).*\(5, 2\)"):
        fuse_points(level, np.zeros((5, 2)), 0.01, t_ns=0)
    pts = np.array([[0.1, 0.1, 0.0], [np.inf, 0.0, 0.0], [0.1, np.nan, 1.0], [100.0, 0, 0]])
    stats = fuse_points(level, pts, 0.01, t_ns=0)
    assert stats.dropped_nonfinite == 2 and stats.outside == 1
    assert level.window("count").sum() == 1


def test_stack_refuses_bad_levels_and_survives_a_teleport() -> None:
    from maps.stack import StackError

    with pytest.raises(StackError, match="increasing"):
        MapStack(StackConfig(levels=(LevelConfig("a", 1.0, 8), LevelConfig("b", 0.5, 8))))
    with pytest.raises(StackError, match="unique"):
        MapStack(StackConfig(levels=(LevelConfig("a", 1.0, 8), LevelConfig("a", 2.0, 8))))
    stack = MapStack()
    with pytest.raises(StackError, match=r"no level 'nope'; levels: .*subsystem"):
        stack.level("nope")
    with pytest.raises(FusionError, match="variance_m2 or sensor_xyz"):
        stack.fuse(np.zeros((3, 3)), t_ns=0)
    stack.fuse(np.array([[0.1, 0.1, 0.0]]), sensor_xyz=[0.0, 0.0, 2.0], t_ns=0)
    assert stack.level("subsystem").window("count").sum() == 1
    stack.move_to(np.array([5e5, 5e5]))  # a jump far beyond every window
    assert all(lvl.window("count").sum() == 0 for lvl in stack.levels)
    stack.move_to(np.zeros(2))  # and back: the tile store restores the kept levels
    assert stack.level("subsystem").window("count").sum() == 1
    assert stack.level("primitive").window("count").sum() == 0  # level 2 keeps no tiles


# --- ray casting: what the beams free (their cells against plain geometry: the kernel harness)


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
