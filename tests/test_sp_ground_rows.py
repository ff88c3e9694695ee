"""A low object far out, met by one row, stands out of its row (:func:`sp.ground.raised_in_rows`).

Scenes are ray-cast analytically: a 64-beam sensor 1.8 m over the terrain (beams every
0.635 degrees, as the simulator's), its low beams only, over a sector of azimuth.
"""

from __future__ import annotations

import numpy as np
import pytest

from sp.ground import GroundConfig, GroundError, ground_mask, raised_in_rows

SENSOR_H = 1.8
W = 1024
EL = np.deg2rad(-25.0 + 40.0 / 63.0 * np.arange(36, 19, -1))  # -2.1 .. -12.3 deg, row 0 highest
T = np.arange(5.0, 60.0, 0.05)  # marching steps along each ray (m)


def _rays(cols: np.ndarray) -> np.ndarray:
    """(H, C, 3) unit rays of the rows ``EL`` at the columns ``cols`` (azimuth pi at column 0
    down to -pi, as the egosphere image runs)."""
    az = np.pi - (cols + 0.5) * 2 * np.pi / W
    E, A = np.meshgrid(EL, az, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)


def cast(terrain, rocks=(), centre_col: int = W // 2, half_cols: int = 80):
    """Ray-cast ``terrain`` (x, y) -> height above the sensor's foot (m) and ``rocks``,
    ellipsoids (centre x, centre y, length, width, height) standing on it as the simulator
    stands them (centre 0.35 of the height up), over columns ``centre_col`` +- ``half_cols``
    (wrapping). Returns xyz (H, W, 3) in the sensor frame (NaN where nothing is hit), valid
    (H, W) and on_rock (H, W) bool."""
    cols = np.arange(centre_col - half_cols, centre_col + half_cols) % W
    d = _rays(cols)
    p = d[:, :, None, :] * T[None, None, :, None]
    inside = p[..., 2] <= -SENSOR_H + terrain(p[..., 0], p[..., 1])
    t_hit = np.where(inside.any(-1), T[np.argmax(inside, axis=-1)], np.inf)
    t_rock = np.full(t_hit.shape, np.inf)
    for x, y, ln, wd, ht in rocks:
        c = np.array([x, y, -SENSOR_H + terrain(np.array(x), np.array(y)) + 0.35 * ht])
        s = np.array([ln / 2, wd / 2, ht / 2])
        # |(t d - c) / s| = 1: a t^2 - 2 b t + k = 0
        a = ((d / s) ** 2).sum(-1)
        b = (d * c / s**2).sum(-1)
        k = ((c / s) ** 2).sum() - 1.0
        disc = b * b - a * k
        t = np.where(disc >= 0, (b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
        t_rock = np.minimum(t_rock, np.where(t > 0, t, np.inf))
    rock_hit = t_rock < t_hit
    t_hit = np.minimum(t_hit, t_rock)
    xyz = np.full((len(EL), W, 3), np.nan)
    valid = np.zeros((len(EL), W), dtype=bool)
    on_rock = np.zeros((len(EL), W), dtype=bool)
    ok = np.isfinite(t_hit)
    xyz[:, cols] = np.where(ok[..., None], d * np.where(ok, t_hit, 0.0)[..., None], np.nan)
    valid[:, cols] = ok
    on_rock[:, cols] = rock_hit & ok
    return xyz, valid, on_rock


def flat(x, y):
    return np.zeros(np.broadcast(x, y).shape)


def rolling(seed: int):
    """Hills (4 m over 150 m wavelengths) and 5 cm RMS roughness over 2-8 m, as the open
    world's terrain, from seeded sinusoids."""
    rng = np.random.default_rng(seed)

    def waves(n, wavelength, scale):
        lam = wavelength * rng.uniform(0.5, 2.0, n)
        th = rng.uniform(0, np.pi, n)
        ph = rng.uniform(0, 2 * np.pi, n)
        kx, ky = 2 * np.pi * np.cos(th) / lam, 2 * np.pi * np.sin(th) / lam
        return kx, ky, ph, np.full(n, scale)

    hills = waves(5, 150.0, 4.0 / 5)
    rough = waves(16, 4.0, 0.05 * np.sqrt(2.0 / 16))

    def h(x, y):
        out = np.zeros(np.broadcast(x, y).shape)
        for kx, ky, ph, amp in (hills, rough):
            for i in range(len(kx)):
                out = out + amp[i] * (np.cos(kx[i] * x + ky[i] * y + ph[i]) - np.cos(ph[i]))
        return out

    return h


ROCK = (40.0, 0.0, 3.0, 2.0, 0.8)  # 40 m ahead, 3 m long, 2 m wide, 0.8 m high


def test_a_low_rock_far_out_is_ground_to_its_columns_and_raised_in_its_row() -> None:
    # one row meets the rock, 0.33-0.36 m up: a gentle rise from the ground 8 m in front,
    # which the column walk and the refinement take for ground
    xyz, valid, rock = cast(flat, rocks=[ROCK])
    assert np.count_nonzero(rock) >= 6
    assert len(set(np.nonzero(rock)[0])) == 1
    ground, _ = ground_mask(xyz, valid)
    assert (ground[rock]).all()
    raised = raised_in_rows(xyz, valid, ground)
    # its row shows it: nearer than the ground the same row meets on both sides of it
    assert np.array_equal(raised, rock)


def test_the_rock_is_found_across_the_azimuth_seam() -> None:
    # the same rock straight behind the sensor, its returns in the image's first and last
    # columns
    xyz, valid, rock = cast(flat, rocks=[(-40.0, 0.0, 3.0, 2.0, 0.8)], centre_col=0)
    assert rock[:, :3].any() and rock[:, -3:].any()
    ground, _ = ground_mask(xyz, valid)
    assert np.array_equal(raised_in_rows(xyz, valid, ground), rock & ground)
    assert np.count_nonzero(rock & ground) >= 6


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_rolling_rough_terrain_has_nothing_raised(seed: int) -> None:
    terrain = rolling(seed)
    xyz, valid, _ = cast(terrain)
    ground, _ = ground_mask(xyz, valid)
    assert np.count_nonzero(ground) > 0.9 * np.count_nonzero(valid)
    assert not raised_in_rows(xyz, valid, ground).any()
    # with rocks on it, nothing but rocks
    rocks = [(40.0, 3.0, 3.0, 2.0, 0.8), (38.0, -2.0, 2.5, 2.5, 0.7), (25.0, 4.0, 1.0, 1.0, 0.5)]
    xyz, valid, rock = cast(terrain, rocks=rocks)
    ground, _ = ground_mask(xyz, valid)
    assert not (raised_in_rows(xyz, valid, ground) & ~rock).any()


def test_a_curb_a_low_mound_and_a_wide_low_body_are_not_raised() -> None:
    def curb(x, y):  # a 15 cm curb along the way, 4 m to the left
        return np.where(y > 4.0, 0.15, 0.0) + 0 * x

    def mound(x, y):  # 0.3 m high, 12 m across, 35 m ahead
        d = np.hypot(x - 35.0, y)
        return np.where(d < 6.0, 0.15 * (1 + np.cos(np.pi * d / 6.0)), 0.0)

    for terrain in (curb, mound):
        xyz, valid, _ = cast(terrain)
        ground, _ = ground_mask(xyz, valid)
        assert not raised_in_rows(xyz, valid, ground).any()
    # a body 8 m across and 0.8 m high is wider than a rock or a bush: left to level 4 ...
    xyz, valid, rock = cast(flat, rocks=[(40.0, 0.0, 2.0, 8.0, 0.8)])
    ground, _ = ground_mask(xyz, valid)
    assert np.count_nonzero(rock & ground) >= 20
    assert not raised_in_rows(xyz, valid, ground).any()
    # ... unless the limit is raised over it
    wide = GroundConfig(raised_max_width_m=9.0)
    assert np.array_equal(raised_in_rows(xyz, valid, ground, wide), rock & ground)
    # and the 3 m rock is raised no more once the limit is below it
    xyz, valid, _ = cast(flat, rocks=[ROCK])
    ground, _ = ground_mask(xyz, valid)
    narrow = GroundConfig(raised_max_width_m=1.0)
    assert not raised_in_rows(xyz, valid, ground, narrow).any()


def test_raised_m_is_the_height_over_the_ground_line() -> None:
    # on flat ground the line from the ground in front to the ground beside is the ground
    xyz, valid, rock = cast(flat, rocks=[ROCK])
    ground, _ = ground_mask(xyz, valid)
    height = xyz[..., 2] + SENSOR_H
    assert (height[rock] > 0.3).all() and (height[rock] < 0.4).all()
    for limit in (0.2, 0.3, 0.35, 0.4):
        raised = raised_in_rows(xyz, valid, ground, GroundConfig(raised_m=limit))
        assert np.array_equal(raised, rock & (height > limit))
    assert not raised_in_rows(xyz, valid, ground, GroundConfig(raised_m=0.4)).any()


def test_bad_shapes_and_limits_are_refused() -> None:
    xyz, valid, _ = cast(flat)
    with pytest.raises(GroundError, match="does not match valid"):
        raised_in_rows(xyz[:, :-1], valid, valid)
    with pytest.raises(GroundError, match="ground shape"):
        raised_in_rows(xyz, valid, valid[:, :-1])
    with pytest.raises(GroundError, match=r"raised_m 0\.0"):
        GroundConfig(raised_m=0.0)
    with pytest.raises(GroundError, match=r"raised_continuity -1\.0"):
        GroundConfig(raised_continuity=-1.0)
    with pytest.raises(GroundError, match=r"raised_dropouts -1"):
        GroundConfig(raised_dropouts=-1)
    with pytest.raises(GroundError, match=r"raised_min_returns 0"):
        GroundConfig(raised_min_returns=0)


def test_the_upper_row_on_a_rock_the_walk_saw_is_raised_over_its_lower_row() -> None:
    # 33 m out, two rows meet the rock: the lower 0.23 m up, which the column walk takes for
    # ground, the upper 0.58 m up, which it does not. Over that lower row the rock stands
    # 0.35 m, under level 4's least object height: the row shows it standing all the same
    xyz, valid, rock = cast(flat, rocks=[(33.0, 0.0, 2.0, 2.0, 0.8)])
    ground, _ = ground_mask(xyz, valid)
    height = xyz[..., 2] + SENSOR_H
    lower, upper = rock & (height < 0.3), rock & (height > 0.5)
    assert np.count_nonzero(lower) >= 6 and np.count_nonzero(upper) >= 4
    assert ground[lower].all() and not ground[upper].any()
    # the lower row stands over the ground line by its own 0.23 m: raised too at 0.2 m
    assert np.array_equal(raised_in_rows(xyz, valid, ground), upper | lower)
    above_lower = GroundConfig(raised_m=0.3)
    assert np.array_equal(raised_in_rows(xyz, valid, ground, above_lower), upper)


def test_neighbours_a_few_dropouts_away_still_show_the_piece() -> None:
    # the rock's row loses the two returns on each side of it (far out a sensor drops
    # returns): its neighbours lie past the dropouts
    xyz, valid, rock = cast(flat, rocks=[ROCK])
    (row,) = set(np.nonzero(rock)[0])
    cols = np.flatnonzero(rock[row])
    for j in (*range(cols[0] - 2, cols[0]), *range(cols[-1] + 1, cols[-1] + 3)):
        valid[row, j] = False
    ground, _ = ground_mask(xyz, valid)
    assert np.array_equal(raised_in_rows(xyz, valid, ground), rock)
    # one dropout allowed: the cuts are gaps, not steps to farther returns
    assert not raised_in_rows(xyz, valid, ground, GroundConfig(raised_dropouts=1)).any()
    # a gap wider than raised_dropouts: no neighbour
    for j in (cols[0] - 3, cols[0] - 4, cols[-1] + 3, cols[-1] + 4):
        valid[row, j] = False
    assert not raised_in_rows(xyz, valid, ground).any()


def test_a_row_empty_on_one_side_still_shows_the_piece_by_the_other() -> None:
    # the rock's row meets nothing for 12 columns on its right (near the horizon its beams
    # pass it and meet no ground within range): the step to the ground on its left shows it
    xyz, valid, rock = cast(flat, rocks=[ROCK])
    (row,) = set(np.nonzero(rock)[0])
    cols = np.flatnonzero(rock[row])
    right = np.arange(cols[-1] + 1, cols[-1] + 13)
    valid[row, right] = False
    xyz[row, right] = np.nan
    ground, _ = ground_mask(xyz, valid)
    assert np.array_equal(raised_in_rows(xyz, valid, ground), rock)
    # ... but not when the next return past the empty columns is nearer than the rock
    past = cols[-1] + 13
    assert valid[row, past]
    nearer = xyz.copy()
    nearer[row, past] *= 0.5
    assert not raised_in_rows(nearer, valid, ground).any()
    # ... nor when the row is empty on both sides: no step to farther returns shows it
    left = np.arange(cols[0] - 12, cols[0])
    valid[row, left] = False
    xyz[row, left] = np.nan
    ground, _ = ground_mask(xyz, valid)
    assert not raised_in_rows(xyz, valid, ground).any()


def test_a_piece_of_fewer_than_raised_min_returns_is_not_raised() -> None:
    # a crest's bump far out stands out of its row over one to three columns: too little to
    # tell from a rock. The rock's piece holds as many returns as its columns
    xyz, valid, rock = cast(flat, rocks=[ROCK])
    ground, _ = ground_mask(xyz, valid)
    n = int(np.count_nonzero(rock))
    assert n >= GroundConfig().raised_min_returns
    at_n = GroundConfig(raised_min_returns=n)
    assert np.array_equal(raised_in_rows(xyz, valid, ground, at_n), rock)
    over = GroundConfig(raised_min_returns=n + 1)
    assert not raised_in_rows(xyz, valid, ground, over).any()
    # a 0.5 m rock 40 m out spans three columns: not raised
    xyz, valid, small = cast(flat, rocks=[(40.0, 0.0, 0.5, 0.5, 0.8)])
    ground, _ = ground_mask(xyz, valid)
    assert 1 <= np.count_nonzero(small) < GroundConfig().raised_min_returns
    assert not raised_in_rows(xyz, valid, ground).any()
    assert np.array_equal(
        raised_in_rows(xyz, valid, ground, GroundConfig(raised_min_returns=1)), small & ground
    )
