"""The column walk leaves the foot of a face to the object over it (``GroundConfig.face_slope_deg``,
``foot_rise_m``): far out, the ground's rows lie metres apart, and the lowest row on a car
passes the walk's slope test from the ground in front; the row above it, at the same range,
shows a face.

Scenes are ray-cast analytically (``test_sp_ground_rows.cast``); a body is part of the height
field there, so its sides are vertical faces.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_sp_ground_rows import SENSOR_H, cast, flat, rolling

from sp.ground import GroundConfig, GroundError, ground_mask

NO_FOOT_RULE = GroundConfig(foot_rise_m=np.inf)


def with_body(terrain, x0: float, x1: float, y0: float, y1: float, height_m: float):
    """``terrain`` with a block (x0..x1, y0..y1 m) standing ``height_m`` on it, and a test of
    which points (..., 3) in the sensor frame lie on the block (on its faces or top)."""

    def h(x, y):
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        return terrain(x, y) + np.where(inside, height_m, 0.0)

    def on(xyz):
        x, y = xyz[..., 0], xyz[..., 1]
        near = (x >= x0 - 0.06) & (x <= x1 + 0.06) & (y >= y0 - 0.06) & (y <= y1 + 0.06)
        return near & (xyz[..., 2] + SENSOR_H - terrain(x, y) > 0.1)

    return h, on


@pytest.mark.parametrize("x0", [31.5, 32.5, 33.0])
def test_the_lowest_row_on_a_far_car_is_not_ground(x0: float) -> None:
    # a car-sized block 1.5 m high, its side to the sensor, past the row that meets the
    # ground at 30.2 m: the next row meets the car 0.19-0.27 m up
    terrain, on = with_body(flat, x0, x0 + 1.8, -2.25, 2.25, 1.5)
    xyz, valid, _ = cast(terrain)
    car = valid & on(np.nan_to_num(xyz))
    height = xyz[..., 2] + SENSOR_H
    assert np.count_nonzero(car) >= 40
    # without the rule the walk takes the car's lowest row for ground ...
    before, _ = ground_mask(xyz, valid, NO_FOOT_RULE)
    foot = car & before
    assert np.count_nonzero(foot) >= 10
    assert (height[foot] > 0.15).all()
    # ... with it, none of the car is ground, and all the ground in front still is
    after, _ = ground_mask(xyz, valid)
    assert not (after & car).any()
    assert np.array_equal(after & ~car, before & ~car)


def test_a_near_wall_keeps_the_low_returns_at_its_foot() -> None:
    # near, the rows meet the ground every few decimetres: the returns low on a wall 8 m out
    # (0.05 m and 0.14 m up) follow the ground in front by less than foot_rise_m, and the rule
    # leaves them as the walk had them
    terrain, _ = with_body(flat, 8.0, 8.5, -4.0, 4.0, 2.0)
    xyz, valid, _ = cast(terrain)
    ground, _ = ground_mask(xyz, valid)
    before, _ = ground_mask(xyz, valid, NO_FOOT_RULE)
    assert np.array_equal(ground, before)
    # with foot_rise_m at zero they go to the wall: only they, low at its face
    zero, _ = ground_mask(xyz, valid, GroundConfig(foot_rise_m=0.0))
    moved = before & ~zero
    assert np.count_nonzero(moved) >= 100
    x = xyz[..., 0]
    assert (x[moved] > 7.9).all() and (x[moved] < 8.1).all()
    assert (xyz[..., 2][moved] + SENSOR_H < 0.15).all()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_rough_rolling_terrain_and_a_curb_have_no_foot(seed: int) -> None:
    terrain = rolling(seed)

    def curb(x, y):  # a 15 cm curb 4 m to the left, on the same hills
        return terrain(x, y) + np.where(y > 4.0, 0.15, 0.0)

    for t in (terrain, curb):
        xyz, valid, _ = cast(t)
        ground, _ = ground_mask(xyz, valid)
        assert np.array_equal(ground, ground_mask(xyz, valid, NO_FOOT_RULE)[0])
        assert np.count_nonzero(ground) > 0.9 * np.count_nonzero(valid)


@pytest.mark.parametrize(("lean_deg", "is_face"), [(60.0, True), (40.0, False)])
def test_a_face_is_steeper_than_face_slope_deg(lean_deg: float, is_face: bool) -> None:
    # the car's side leaning back: two rows meet it, 0.2-0.6 m up; the walk takes the lower
    # for ground, and the rule takes it back only when the side is steeper than 45 degrees
    def leaning(x, y):
        rise = np.clip((x - 31.5) * np.tan(np.deg2rad(lean_deg)), 0.0, 1.5)
        return np.where(np.abs(y) <= 2.25, rise, 0.0)

    xyz, valid, _ = cast(leaning)
    height = np.nan_to_num(xyz[..., 2]) + SENSOR_H
    # (away from its ends, where the upper row passes it)
    side = valid & (height > 0.15) & (np.abs(np.nan_to_num(xyz[..., 1])) < 1.8)
    before, _ = ground_mask(xyz, valid, NO_FOOT_RULE)
    assert np.count_nonzero(before & side) >= 10
    ground, _ = ground_mask(xyz, valid)
    assert np.array_equal(ground & side, np.zeros_like(side) if is_face else before & side)
    # a face angle under the lean makes it a face
    gentler, _ = ground_mask(xyz, valid, GroundConfig(face_slope_deg=lean_deg - 5.0))
    assert not (gentler & side).any()


def test_bad_face_limits_are_refused() -> None:
    with pytest.raises(GroundError, match=r"face_slope_deg 0\.0"):
        GroundConfig(face_slope_deg=0.0)
    with pytest.raises(GroundError, match=r"foot_rise_m -0\.1"):
        GroundConfig(foot_rise_m=-0.1)
