"""One map level: index transforms, toroidal scrolling, tiles, selections, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from maps import submap
from maps.layers import LayerSpec, with_current_names
from maps.level import LevelConfig, LevelError, MapLevel
from maps.tiles import InMemoryTileStore

RES = 0.5
SIZE = 12

moves = st.tuples(st.floats(-40, 40), st.floats(-40, 40))
ops = st.lists(
    st.one_of(
        st.tuples(st.just("move"), moves),
        st.tuples(st.just("write"), st.tuples(st.integers(0, SIZE - 1), st.integers(0, SIZE - 1))),
        st.tuples(st.just("step"), st.tuples(st.integers(-3, 3), st.integers(-3, 3))),
    ),
    min_size=1,
    max_size=40,
)


def _cell_xy(level: MapLevel, row: int, col: int) -> np.ndarray:
    return level.window_to_world(np.array([row]), np.array([col]))


def _run(level: MapLevel, script, keep: bool) -> None:
    """Replay ``script``; check every written cell against a dict model after each step."""
    written: dict[tuple[int, int], float] = {}
    left: set[tuple[int, int]] = set()
    counter = 0.0
    for kind, arg in script:
        if kind == "write":
            xy = _cell_xy(level, *arg)
            counter += 1.0
            level.write("elevation", xy, counter)
            cell = tuple(int(v) for v in level.world_to_cell(xy)[0])
            written[cell] = counter
            left.discard(cell)
        else:
            step = RES * np.asarray(arg, float)
            level.move_to(np.asarray(arg, float) if kind == "move" else level.center_xy + step)
        lo = level.origin_cell
        for cell, value in list(written.items()):
            inside = all(lo[k] <= cell[k] < lo[k] + SIZE for k in (0, 1))
            xy = level.cell_to_world(np.array([cell]))
            got = level.read("elevation", xy)[0]
            if inside:
                assert got == value, f"cell {cell} read {got}, wrote {value}"
            elif not keep:
                written.pop(cell)
                left.add(cell)
        for cell in left:  # cleared when it left: must read empty if it is back in the window
            got = level.read("elevation", level.cell_to_world(np.array([cell])))[0]
            assert np.isnan(got)


@settings(max_examples=60, deadline=None)
@given(script=ops)
def test_written_value_reads_back_while_in_window_and_is_cleared_after(script) -> None:
    level = MapLevel(LevelConfig("t", RES, SIZE, keep_tiles=False))
    _run(level, script, keep=False)


@settings(max_examples=60, deadline=None)
@given(script=ops, tile=st.integers(1, 7))
def test_tiles_bring_back_every_written_value(script, tile: int) -> None:
    level = MapLevel(LevelConfig("t", RES, SIZE, tile_cells=tile), InMemoryTileStore())
    _run(level, script, keep=True)


def test_index_transforms_round_trip() -> None:
    level = MapLevel(LevelConfig("t", 0.4, 256))
    level.move_to(np.array([1000.3, -507.9]))
    rng = np.random.default_rng(1)
    rows, cols = rng.integers(0, 256, 500), rng.integers(0, 256, 500)
    xy = level.window_to_world(rows, cols)
    r2, c2, inside = level.world_to_window(xy)
    assert inside.all() and np.array_equal(r2, rows) and np.array_equal(c2, cols)
    # the window centre is the vehicle position, to within one cell
    assert np.all(np.abs(level.center_xy - [1000.3, -507.9]) <= 0.4)


def test_window_is_in_world_order_with_no_wrap() -> None:
    level = MapLevel(LevelConfig("t", 1.0, 8, keep_tiles=False))
    level.move_to(np.array([3.7, -2.2]))
    xy = level.window_to_world(*np.nonzero(np.ones((8, 8))))
    level.write("elevation", xy, xy[:, 0] * 100 + xy[:, 1])
    level.move_to(np.array([6.7, 0.8]))  # 3 cells east and north: storage now wraps
    win = level.window("elevation")
    centres = level.window_to_world(*np.nonzero(np.ones((8, 8)))).reshape(8, 8, 2)
    expect = centres[..., 0] * 100 + centres[..., 1]
    known = np.isfinite(win)
    assert known.sum() == 5 * 5
    np.testing.assert_allclose(win[known], expect[known], rtol=1e-6)
    assert not known[5:, :].any() and not known[:, 5:].any()  # the new rows/cols are empty


def test_teleport_clears_without_error() -> None:
    level = MapLevel(LevelConfig("t", 1.0, 16, keep_tiles=False))
    level.write("elevation", np.array([[0.2, 0.3]]), 5.0)
    level.move_to(np.array([1e6, -1e6]))
    assert np.isnan(level.window("elevation")).all()
    level.move_to(np.array([0.0, 0.0]))
    assert np.isnan(level.window("elevation")).all()


def test_loop_route_restores_old_map() -> None:
    store = InMemoryTileStore()
    level = MapLevel(LevelConfig("t", 1.0, 32, tile_cells=8), store)
    rr, cc = np.nonzero(np.ones((32, 32)))
    xy = level.window_to_world(rr, cc)
    level.write("elevation", xy, np.sin(xy[:, 0]) + xy[:, 1])
    before = level.window("elevation")
    for p in ([40, 0], [80, 40], [40, 80], [0, 40], [0, 0]):  # a loop far from the start
        level.move_to(np.array(p, float))
    assert len(store) > 0
    np.testing.assert_array_equal(level.window("elevation"), before)


def test_a_new_level_over_a_filled_store_starts_from_it_and_keeps_it() -> None:
    """A second run over the same store: its first window comes from the stored tiles, and
    its first move must not overwrite them with the empty cells it started with."""
    store = InMemoryTileStore()
    first = MapLevel(LevelConfig("t", 1.0, 32, tile_cells=8), store)
    rr, cc = np.nonzero(np.ones((32, 32)))
    xy = first.window_to_world(rr, cc)
    first.write("elevation", xy, np.cos(xy[:, 0]) - xy[:, 1])
    before = first.window("elevation")
    assert first.keep_window() == 16  # 32 x 32 cells in 8 x 8 tiles
    second = MapLevel(LevelConfig("t", 1.0, 32, tile_cells=8), store)
    np.testing.assert_array_equal(second.window("elevation"), before)
    second.move_to(np.array([20.0, 0.0]))  # half the window leaves, then comes back
    second.move_to(np.array([0.0, 0.0]))
    np.testing.assert_array_equal(second.window("elevation"), before)


def test_selections_match_cell_centres() -> None:
    level = MapLevel(LevelConfig("t", 0.5, 40))
    level.move_to(np.array([10.0, 5.0]))
    r, c = submap.box(level, [8.0, 4.0], [9.9, 6.1])
    xy = level.window_to_world(r, c)
    assert np.all((xy >= [8.0, 4.0]) & (xy <= [9.9, 6.1]))
    assert len(r) == 4 * 4  # centres 8.25..9.75 and 4.25..5.75
    r, c = submap.circle(level, [10.0, 5.0], 2.0)
    d = np.linalg.norm(level.window_to_world(r, c) - [10.0, 5.0], axis=1)
    rr, cc = np.nonzero(np.ones((40, 40)))
    all_xy = level.window_to_world(rr, cc)
    assert np.all(d <= 2.0) and len(r) == int((np.linalg.norm(all_xy - [10, 5], axis=1) <= 2).sum())
    tri = np.array([[5.0, 0.0], [15.0, 0.0], [5.0, 10.0]])
    r, c = submap.polygon(level, tri)
    xy = level.window_to_world(r, c)
    assert np.all(xy[:, 0] + xy[:, 1] < 15.0) and np.all(xy >= [5.0, 0.0])
    inside = (all_xy[:, 0] > 5) & (all_xy[:, 1] > 0) & (all_xy.sum(1) < 15)
    assert len(r) == int(inside.sum())
    r, c = submap.line(level, [5.1, 5.1], [12.9, 5.1])
    assert np.all(r == r[0]) and np.array_equal(c, np.arange(c[0], c[0] + 16))


def test_bad_input_is_refused_with_what_is_valid() -> None:
    with pytest.raises(LevelError, match="resolution_m must be > 0"):
        MapLevel(LevelConfig("t", 0.0))
    with pytest.raises(LevelError, match="resolution_m must be > 0"):
        MapLevel(LevelConfig("t", -1.0))
    level = MapLevel(LevelConfig("t", 1.0, 8))
    with pytest.raises(LevelError, match=r"valid layers: .*elevation"):
        level.window("elevations")
    with pytest.raises(LevelError, match=r"needs shape \(8, 8\)"):
        level.set_window("elevation", np.zeros((7, 8)))
    with pytest.raises(LevelError, match=r"must be \(N, 2\)"):
        level.read("elevation", np.zeros(3))
    with pytest.raises(LevelError, match="specified twice"):
        twice = (LayerSpec("a", "f4", 0), LayerSpec("a", "f4", 0))
        MapLevel(LevelConfig("t", 1.0, 8, layers=twice))


def test_layers_stored_under_an_earlier_name_come_back_under_the_current_one() -> None:
    old, new = np.zeros((2, 2)), np.ones((2, 2))
    tile = {"elevation": new}
    assert with_current_names(tile) is tile  # nothing renamed: the same dict
    got = with_current_names({"z_m2": old, "elevation": new})
    assert set(got) == {"z_sq_dev_sum", "elevation"} and got["z_sq_dev_sum"] is old
    both = with_current_names({"z_m2": old, "z_sq_dev_sum": new})
    assert set(both) == {"z_sq_dev_sum"} and both["z_sq_dev_sum"] is new
