"""Terrain layers against known answers: slope of tilted planes, step height at a known step,
traversability at and beyond the configured limits, roughness from noise of known sigma, and
unknown (NaN) cells, whose effect must stay within what ``maps.terrain`` documents."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from kernel_reference.terrain_reference import terrain_layers_reference

from maps.fusion import fuse_points
from maps.level import LevelConfig, MapLevel
from maps.terrain import TerrainConfig, step_heights, update_terrain

SIZE = 32
INNER = (slice(1, -1), slice(1, -1))  # cells whose 8 neighbours are all in the window


def _level(res: float = 0.4, size: int = SIZE, center=(0.0, 0.0)) -> MapLevel:
    level = MapLevel(LevelConfig("t", res, size, keep_tiles=False))
    level.move_to(np.asarray(center, dtype=float))
    return level


def _set_height(level: MapLevel, fn) -> np.ndarray:
    """Write elevation ``fn(x, y)`` at every cell centre through world coordinates; returns the
    written heights in window order."""
    rows, cols = np.indices((level.size, level.size))
    xy = level.window_to_world(rows.ravel(), cols.ravel())
    z = np.asarray(fn(xy[:, 0], xy[:, 1]), dtype=np.float64)
    level.write("elevation", xy, z)
    return z.reshape(level.size, level.size)


def _plane(theta: float, azimuth: float):
    """Height of a plane rising at angle ``theta`` (rad) towards ``azimuth`` (rad from +x)."""
    a, b = np.tan(theta) * np.cos(azimuth), np.tan(theta) * np.sin(azimuth)
    return lambda x, y: 1.5 + a * x + b * y


@pytest.mark.parametrize("theta", [0.05, 0.3, 0.6, 1.0])
@pytest.mark.parametrize("azimuth_deg", [0.0, 90.0, 30.0, 225.0])
def test_tilted_plane_slope_is_its_angle_in_radians(theta: float, azimuth_deg: float) -> None:
    level = _level()
    _set_height(level, _plane(theta, np.radians(azimuth_deg)))
    update_terrain(level)
    slope = level.window("slope")
    np.testing.assert_allclose(slope[INNER], theta, atol=2e-5)  # layer unit: rad
    # the window's edge ring lacks a neighbour on one side: one-sided differences, exact on a
    # plane too
    np.testing.assert_allclose(slope, theta, atol=2e-5)
    # largest 8-neighbour difference of a plane: a diagonal (or axis) step of res * |grad|_1
    az = np.radians(azimuth_deg)
    step = 0.4 * np.tan(theta) * (abs(np.cos(az)) + abs(np.sin(az)))
    np.testing.assert_allclose(level.window("step_height")[INNER], step, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("height", [0.2, 0.5])
def test_step_of_known_height_shows_at_its_edge_only(height: float) -> None:
    res = 0.4
    level = _level(res)
    z = _set_height(level, lambda x, y: np.where(x < 0.0, 2.0, 2.0 + height))
    edge = np.zeros((SIZE, SIZE), bool)
    lo_col = int(np.nonzero(z[0] > 2.0)[0][0])  # first column on the high side
    edge[:, [lo_col - 1, lo_col]] = True
    update_terrain(level)
    step = level.window("step_height")
    np.testing.assert_allclose(step[edge], height, rtol=1e-5)
    np.testing.assert_array_equal(step[~edge], 0.0)
    # slope: central difference across the edge, height / (2 res), zero elsewhere inside
    slope = level.window("slope")
    inner_edge = edge.copy()
    inner_edge[[0, -1], :] = False
    np.testing.assert_allclose(slope[inner_edge], np.arctan(height / (2 * res)), rtol=1e-5)
    inner_rest = ~edge
    inner_rest[[0, -1], :] = inner_rest[:, [0, -1]] = False
    np.testing.assert_array_equal(slope[inner_rest], 0.0)
    trav = level.window("traversability")
    np.testing.assert_array_equal(trav[~edge], 1.0)  # flat away from the step: easy
    assert TerrainConfig().max_step_m == 0.3
    if height > TerrainConfig().max_step_m:
        np.testing.assert_array_equal(trav[edge], 0.0)  # beyond the step limit: impassable
    else:
        assert (trav[edge] > 0.0).all() and (trav[edge] < 1.0).all()


def test_flat_plane_is_flat_and_fully_traversable() -> None:
    level = _level(center=(3.3, -2.1))
    _set_height(level, lambda x, y: np.full_like(x, 7.25))
    update_terrain(level)
    np.testing.assert_array_equal(level.window("slope")[INNER], 0.0)
    np.testing.assert_array_equal(level.window("step_height"), 0.0)
    np.testing.assert_array_equal(level.window("traversability"), 1.0)


def test_slope_beyond_the_limit_is_impassable() -> None:
    cfg = TerrainConfig()
    res = 0.04  # fine cells: a plane's steps stay far below max_step_m, only the slope counts
    trav = {}
    for theta in (0.1, 0.3, cfg.max_slope_rad - 0.02, cfg.max_slope_rad + 0.02, 1.0):
        level = _level(res)
        _set_height(level, _plane(theta, 0.7))
        update_terrain(level, cfg)
        # the step is never what limits: its share of its limit stays below the slope's
        assert np.nanmax(level.window("step_height")) / cfg.max_step_m < theta / cfg.max_slope_rad
        t = level.window("traversability")[INNER]
        assert np.ptp(t) < 1e-5  # a plane is equally passable everywhere
        trav[theta] = float(t.mean())
    values = list(trav.values())
    assert values[0] > values[1] > values[2] > 0.0  # steeper -> harder, passable below the limit
    assert values[3] == 0.0 and values[4] == 0.0  # beyond max_slope_rad: impassable
    # the limit comes from the config: a laxer one lets the same slope through
    level = _level(res)
    _set_height(level, _plane(cfg.max_slope_rad + 0.02, 0.7))
    update_terrain(level, TerrainConfig(max_slope_rad=0.8))
    assert (level.window("traversability")[INNER] > 0.0).all()


def test_step_limit_comes_from_the_config() -> None:
    level = _level()
    _set_height(level, lambda x, y: np.where(x < 0.0, 0.0, 0.5))
    update_terrain(level, TerrainConfig(max_step_m=2.0, max_slope_rad=1.5))
    assert np.nanmin(level.window("traversability")) > 0.0
    update_terrain(level, TerrainConfig(max_step_m=0.4, max_slope_rad=1.5))
    assert np.nanmin(level.window("traversability")) == 0.0


def test_occupied_and_rough_cells_are_impassable() -> None:
    cfg = TerrainConfig()
    level = _level()
    _set_height(level, lambda x, y: np.zeros_like(x))
    occ = np.zeros((SIZE, SIZE), np.float32)
    occ[5, 5] = cfg.occupied_log_odds
    occ[5, 7] = cfg.occupied_log_odds - 0.01
    level.set_window("occupancy", occ)
    rough = np.full((SIZE, SIZE), np.nan, np.float32)
    rough[10, 10] = cfg.max_roughness_m + 0.01
    rough[10, 12] = 0.5 * cfg.max_roughness_m
    level.set_window("roughness", rough)
    update_terrain(level, cfg)
    trav = level.window("traversability")
    assert trav[5, 5] == 0.0 and trav[5, 7] == 1.0
    assert trav[10, 10] == 0.0 and 0.0 < trav[10, 12] < 1.0
    others = np.ones((SIZE, SIZE), bool)
    others[5, 5] = others[10, 10] = others[10, 12] = False
    np.testing.assert_array_equal(trav[others], 1.0)


def test_roughness_follows_the_noise_sigma_and_lowers_traversability() -> None:
    """Flat ground fused with Gaussian height noise of known sigma: the roughness layer (the
    weighted std of the cell's ground heights) is about sigma, and traversability falls."""
    rng = np.random.default_rng(3)
    cfg = TerrainConfig()
    size, res, per_cell = 16, 0.4, 400
    got = {}
    for sigma in (0.0, 0.01, 0.03, 0.05):
        level = _level(res, size)
        lo, hi = level.bounds_xy
        n = size * size * per_cell
        xy = rng.uniform(lo + 1e-6, hi - 1e-6, size=(n, 2))
        z = 0.8 + sigma * rng.standard_normal(n)
        fuse_points(level, np.column_stack([xy, z]), variance_m2=1e-4, t_ns=0)
        assert (level.window("count") > 0.8 * per_cell).all()  # noise kept as ground
        update_terrain(level, cfg)
        rough = level.window("roughness")
        got[sigma] = (float(np.median(rough)), float(np.median(level.window("traversability"))))
        if sigma == 0.0:
            assert np.nanmax(rough) < 1e-4
        else:
            np.testing.assert_allclose(np.median(rough), sigma, rtol=0.05)
            assert np.percentile(rough, 5) > 0.85 * sigma
    sigmas = sorted(got)
    trav = [got[s][1] for s in sigmas]
    assert trav[0] > 0.99 and all(a > b for a, b in itertools.pairwise(trav))
    assert trav[-1] < 1.0 - 0.8 * 0.05 / cfg.max_roughness_m


def test_unknown_cells_stay_unknown_and_spare_their_neighbours() -> None:
    """One unknown cell in a plane: it stays NaN in every terrain layer; the step height of its
    neighbours still comes from their known neighbours, and the slope of its 4 axis neighbours
    from one-sided differences (the plane's slope still); nothing else is lost."""
    theta, az = 0.25, 0.4
    level = _level()
    _set_height(level, _plane(theta, az))
    r0, c0 = 12, 20
    level.write("elevation", level.window_to_world(np.array([r0]), np.array([c0])), np.nan)
    update_terrain(level)
    slope, step = level.window("slope"), level.window("step_height")
    trav = level.window("traversability")
    for name, layer in (("slope", slope), ("step_height", step), ("traversability", trav)):
        assert np.isnan(layer[r0, c0]), f"{name} of a cell with no elevation must stay NaN"
    hole = np.zeros((SIZE, SIZE), bool)
    hole[r0, c0] = True
    inner = np.zeros((SIZE, SIZE), bool)
    inner[INNER] = True
    np.testing.assert_array_equal(np.isnan(slope), hole)
    np.testing.assert_allclose(slope[~hole], theta, atol=2e-5)
    plane_step = 0.4 * np.tan(theta) * (abs(np.cos(az)) + abs(np.sin(az)))
    np.testing.assert_allclose(step[inner & ~hole], plane_step, rtol=1e-4)
    np.testing.assert_array_equal(np.isnan(trav), hole)


def test_a_steep_cell_beside_a_hole_is_not_passable() -> None:
    """On 0.04 m cells (where the step limit never binds) a 0.6 rad plane is impassable
    (max_slope_rad 0.5), also right beside a cell with no elevation."""
    level = MapLevel(LevelConfig("fine", 0.04, SIZE, keep_tiles=False))
    _set_height(level, _plane(0.6, 0.0))
    r0, c0 = 12, 20
    level.write("elevation", level.window_to_world(np.array([r0]), np.array([c0])), np.nan)
    update_terrain(level)
    trav = level.window("traversability")
    assert np.isnan(trav[r0, c0])
    assert np.all(trav[[r0 - 1, r0 + 1, r0, r0], [c0, c0, c0 - 1, c0 + 1]] == 0.0)


def test_isolated_known_cell_has_no_terrain() -> None:
    """A known cell whose neighbours are all unknown: its step, slope and traversability stay
    NaN (the module: "Cells ... whose neighbours have none, stay NaN")."""
    level = _level()
    level.write("elevation", level.window_to_world(np.array([9]), np.array([9])), 1.0)
    update_terrain(level)
    for name in ("slope", "step_height", "traversability"):
        assert np.isnan(level.window(name)).all(), name


def test_step_heights_counts_diagonals_and_skips_unknown_neighbours() -> None:
    e = np.zeros((5, 5))
    e[2, 2] = 1.0
    got = step_heights(e)
    want = np.zeros((5, 5))
    want[1:4, 1:4] = 1.0  # the bump and all 8 of its neighbours (diagonals included)
    np.testing.assert_array_equal(got, want)
    e = np.full((3, 3), np.nan)
    e[0, 0], e[1, 1], e[2, 2] = 0.0, 0.5, 2.0  # a diagonal chain; the rest unknown
    e[0, 2] = -1.0
    got = step_heights(e)
    np.testing.assert_allclose(got[0, 0], 0.5)
    np.testing.assert_allclose(got[1, 1], 1.5)  # max(|0.5-0|, |0.5-2|, |0.5+1|)
    np.testing.assert_allclose(got[2, 2], 1.5)
    np.testing.assert_allclose(got[0, 2], 1.5)
    assert np.isnan(got[[0, 1, 1, 2], [1, 0, 2, 1]]).all()  # unknown cells stay NaN


def test_terrain_is_computed_across_the_toroidal_seam() -> None:
    """With the window scrolled so the storage wraps inside it, a plane still has one slope
    and one step everywhere inside (window order: the seam makes no false neighbours)."""
    level = _level(center=(13.3, -7.9))
    assert (level.origin_cell % SIZE != 0).all()  # the seam runs through the window
    theta = 0.3
    _set_height(level, _plane(theta, 0.0))
    update_terrain(level)
    np.testing.assert_allclose(level.window("slope")[INNER], theta, atol=2e-5)
    np.testing.assert_allclose(level.window("step_height")[INNER], 0.4 * np.tan(theta), rtol=1e-4)
    # the raw storage differs from the window (it really wraps) yet holds the same values
    assert not np.array_equal(level.storage("elevation"), level.window("elevation"))


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("p_unknown", [0.0, 0.3, 0.9])
def test_compiled_terrain_equals_the_numpy_form(seed: int, p_unknown: float) -> None:
    """The one-pass kernel gives the layers of the numpy oracle ``terrain_layers_reference``
    (rough terrain with holes, rough and occupied cells, a window whose storage wraps)."""
    level = _level()
    level.move_to(np.array([3.3, -7.9]))  # storage wraps inside the window
    rows, cols = np.indices((SIZE, SIZE))
    xy = level.window_to_world(rows.ravel(), cols.ravel())
    r = np.random.default_rng(seed)
    z = np.cumsum(r.normal(0, 0.15, len(xy))).reshape(SIZE, SIZE) * 0.1
    z[r.random((SIZE, SIZE)) < p_unknown] = np.nan
    level.write("elevation", xy, z.ravel())
    level.write("roughness", xy, r.uniform(0, 0.2, len(xy)))
    level.write("occupancy", xy, r.normal(0, 1.5, len(xy)))
    # the oracle on the window as update_terrain reads it, stored as float32 as it writes it
    e, rough, occ = (
        level.window(n).astype(np.float64) for n in ("elevation", "roughness", "occupancy")
    )
    want = [
        a.astype(np.float32)
        for a in terrain_layers_reference(e, rough, occ, level.resolution_m, TerrainConfig())
    ]
    update_terrain(level, TerrainConfig())
    got = [level.window(n) for n in ("slope", "step_height", "traversability")]
    for name, a, b in zip(("slope", "step", "trav"), got, want, strict=True):
        assert np.array_equal(np.isnan(a), np.isnan(b)), name
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7, equal_nan=True, err_msg=name)
    if p_unknown < 0.5:
        assert np.isfinite(got[2]).mean() > 0.3 and (got[2] == 0).any()
