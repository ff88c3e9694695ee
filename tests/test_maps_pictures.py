"""Pictures: orientation, hill shading, labels, vehicle marker, all levels side by side."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from core.geometry import rot_z, se3
from maps.level import LevelConfig, MapLevel
from maps.pictures import (
    LEGEND_PX,
    NO_DATA_BGR,
    PictureError,
    hillshade,
    label_colours,
    render_layer,
    render_levels,
    save_png,
)
from maps.stack import MapStack


def _level_with_ramp() -> MapLevel:
    """A 64 x 64 level, 1 m cells, elevation = y (rising to the north); east half unknown."""
    level = MapLevel(LevelConfig("t", 1.0, 64))
    level.move_to(np.array([0.0, 0.0]))
    rr, cc = np.nonzero(np.ones((64, 64)))
    xy = level.window_to_world(rr, cc)
    level.write("elevation", xy, np.where(xy[:, 0] < 0, xy[:, 1], np.nan))
    return level


def test_north_is_up_and_no_data_is_grey() -> None:
    img = render_layer(_level_with_ramp(), "elevation", scale=2)
    assert img.shape == (128 + LEGEND_PX, 128, 3) and img.dtype == np.uint8
    # turbo runs blue (low) -> red (high): top rows (north, high y) are redder than bottom rows
    top, bottom = img[10, 20].astype(int), img[117, 20].astype(int)
    assert top[2] - top[0] > bottom[2] - bottom[0]
    assert tuple(img[60, 100]) == NO_DATA_BGR  # east half has no data


def test_hillshade_lights_slopes_facing_the_sun() -> None:
    x = np.arange(32, dtype=float)
    facing_west = np.tile(x, (32, 1))  # rises to the east: faces west, towards a 270 deg sun
    facing_east = np.tile(-x, (32, 1))
    west = hillshade(facing_west, 1.0, azimuth_deg=270.0)
    east = hillshade(facing_east, 1.0, azimuth_deg=270.0)
    assert west.mean() > east.mean() + 0.3
    flat = hillshade(np.zeros((8, 8)), 1.0, altitude_deg=90.0)
    np.testing.assert_allclose(flat, 1.0)


def test_vehicle_marker_sits_at_the_body_position() -> None:
    level = _level_with_ramp()
    T = se3(rot_z(0.0), [10.0, -20.0, 0.0])  # 10 m east, 20 m south of the window centre
    img = render_layer(level, "elevation", scale=2, T_world_body=T)
    u, v = (10.0 + 32.0) * 2, 128 - (-20.0 + 32.0) * 2
    red = (img[..., 2] == 255) & (img[..., 0] == 0) & (img[..., 1] == 0)
    ys, xs = np.nonzero(red[:128])
    assert abs(xs.mean() - u) < 3 and abs(ys.mean() - v) < 3


def test_labels_and_overlays_use_one_colour_per_id(tmp_path) -> None:
    level = _level_with_ramp()
    level.write("entity_id", np.array([[-20.5, 10.5], [-19.5, 10.5]]), np.array([7, 9]))
    img = render_layer(level, "entity_id", scale=1)
    r, c = 64 - 1 - (10 + 32), -21 + 32
    assert tuple(img[r, c]) == tuple(label_colours(np.array([7]))[0])
    assert tuple(img[r, c + 1]) == tuple(label_colours(np.array([9]))[0])
    assert tuple(img[0, 0]) == NO_DATA_BGR
    over = render_layer(level, "elevation", scale=1, overlay="entity_id")
    plain = render_layer(level, "elevation", scale=1)
    assert not np.array_equal(over[r, c], plain[r, c]) and np.array_equal(over[5, 5], plain[5, 5])
    path = save_png(over, tmp_path / "pic" / "overlay.png")
    back = cv2.imread(str(path))
    np.testing.assert_array_equal(back, over)


def test_all_levels_side_by_side() -> None:
    stack = MapStack()
    stack.move_to_pose(se3(rot_z(0.3), [5.0, 5.0, 0.0]))
    rng = np.random.default_rng(0)
    xy = rng.uniform(-60, 60, size=(20000, 2)) + 5.0
    stack.fuse(np.column_stack([xy, 0.05 * xy[:, 0]]), variance_m2=1e-3, t_ns=0)
    img = render_levels(stack.levels, "elevation", panel_px=256, T_world_body=stack.T_world_body)
    assert img.shape == (256 + LEGEND_PX, 4 * (256 + 4), 3)
    with pytest.raises(PictureError, match="scale"):
        render_layer(stack.levels[0], scale=0)
