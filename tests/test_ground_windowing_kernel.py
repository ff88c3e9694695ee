"""The compiled ground segmentation (sp.ground.ground_mask) and window fill
(sp.windowing.window_mask) give their numpy references' results exactly: the same ground mask
and the same sensor height (bit for bit) on ray-cast LADAR sweeps with slopes, a curb, boxes,
vegetation, drop-outs and NaN- or zero-filled empty pixels; the same attention mask for windows
that wrap in azimuth, span the image or miss every row; and both on degenerate images."""

from __future__ import annotations

import numpy as np
import pytest
from kernel_reference.ground_reference import (
    column_walk_reference,
    ground_mask_reference,
    refine_reference,
)
from kernel_reference.windowing_reference import window_mask_reference

from sp.ground import (
    GroundConfig,
    GroundError,
    _height_from_lowest,
    _median_height,
    _prepare_kernel,
    column_walk,
    estimate_sensor_height,
    ground_mask,
    refine,
)
from sp.windowing import WindowConfig, WindowingError, window_mask

# the numpy references cast NaN ranges, azimuths and window sizes of empty pixels or
# degenerate windows to int64 (values they then never use)
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")

# ---------------------------------------------------------------- synthetic sweeps


def _rays(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """(h, w, 3) unit rays: rows from +0.3 rad (row 0) down to -0.4 rad with a little jitter
    per row, columns in :mod:`sp.egosphere`'s azimuth order (pi down to -pi)."""
    el = np.linspace(0.3, -0.4, h) + rng.normal(0.0, 1e-3, h)
    az = np.pi - (np.arange(w) + 0.5) * 2 * np.pi / w
    E, A = np.meshgrid(el, az, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)


def _plane_t(d: np.ndarray, height: float, a: float, b: float, dz: float = 0.0) -> np.ndarray:
    """Ray parameter (m) where rays ``d`` meet z = -height + dz + a x + b y (inf if never)."""
    den = d[..., 2] - a * d[..., 0] - b * d[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (-height + dz) / den
    return np.where((den < -1e-6) & (t > 0), t, np.inf)


def _box_t(d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Ray parameter (m) of the first hit of rays ``d`` from the origin on the box [lo, hi]
    (its far side when the origin is inside it)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = lo / d, hi / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
    t = np.where(t_near > 0, t_near, t_far)
    return np.where((t_near <= t_far) & (t > 0), t, np.inf)


def sweep(
    seed: int,
    h: int = 64,
    w: int = 1024,
    fill: str = "nan",
    height: float | None = None,
    quantum_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A ray-cast sweep in the gravity-aligned sensor frame: a sloped ground with a curb
    (a 0.1 m step beyond a line), boxes (cars, a wall) standing on it, range noise, raised
    returns (vegetation), random and column-block drop-outs, no return beyond 120 m.

    Returns xyz (h, w, 3) float64 m, with ``fill`` ("nan", "zero" or "junk") where invalid, and
    valid (h, w) bool. ``quantum_m`` > 0 rounds the coordinates to it, as a sensor's fixed
    resolution does: then the returns of a vertical face share exact ranges (ties).
    """
    rng = np.random.default_rng(seed)
    sensor_h = rng.uniform(1.5, 2.2) if height is None else height
    a, b = rng.uniform(-0.15, 0.15, 2)  # up to ~9 degrees of slope
    d = _rays(h, w, rng)
    t = _plane_t(d, sensor_h, a, b)
    # the curb: beyond y = y0 the ground is 0.1 m higher
    y0 = rng.uniform(3.0, 8.0)
    t_curb = _plane_t(d, sensor_h, a, b, dz=0.1)
    t = np.where(t_curb * d[..., 1] > y0, t_curb, t)
    for _ in range(rng.integers(3, 9)):
        cx, cy = rng.uniform(-40, 40, 2)
        if np.hypot(cx, cy) < 4.0:
            continue
        half = rng.uniform([0.5, 0.5], [3.0, 1.2])
        z0 = -sensor_h + a * cx + b * cy
        lo = np.array([cx - half[0], cy - half[1], z0 - 0.5])
        hi = np.array([cx + half[0], cy + half[1], z0 + rng.uniform(0.4, 3.0)])
        t = np.minimum(t, _box_t(d, lo, hi))
    t = t * (1 + 0.002 * rng.standard_normal(t.shape))
    valid = np.isfinite(t) & (t < 120.0) & (t > 0.5)
    valid &= rng.random(valid.shape) >= 0.05
    for _ in range(3):  # a few blocks of columns with no return (a puddle, an occlusion)
        j = rng.integers(0, w)
        valid[:, j : j + rng.integers(1, 12)] = False
    xyz = np.where(valid[..., None], t[..., None] * d, 0.0)
    xyz[..., 2] += 0.02 * rng.standard_normal(valid.shape)
    xyz[..., 2] += np.where(rng.random(valid.shape) < 0.02, rng.uniform(0.1, 1.5, valid.shape), 0)
    if quantum_m > 0:
        xyz = np.round(xyz / quantum_m) * quantum_m
    xyz[~valid] = {"nan": np.nan, "zero": 0.0, "junk": 1e6}[fill]
    return xyz, valid


def assert_same_ground(xyz: np.ndarray, valid: np.ndarray, cfg: GroundConfig) -> np.ndarray:
    """ground_mask and ground_mask_reference agree exactly; returns the mask."""
    got, h = ground_mask(xyz, valid, cfg)
    want, h_want = ground_mask_reference(xyz, valid, cfg)
    assert got.dtype == np.bool_ and got.shape == valid.shape
    np.testing.assert_array_equal(got, want)
    assert h == h_want  # bit for bit, not approximately
    assert not (got & ~valid).any()
    return got


# ---------------------------------------------------------------- ground: full sweeps


@pytest.mark.parametrize("fill", ["nan", "zero", "junk"])
@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_ground_mask_gives_the_reference_on_sweeps(seed: int, fill: str) -> None:
    xyz, valid = sweep(seed, fill=fill)
    ground = assert_same_ground(xyz, valid, GroundConfig())
    # a real scene: most of the valid returns are ground, the boxes and vegetation are not
    n = np.count_nonzero(valid)
    assert 0.3 * n < np.count_nonzero(ground) < n


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ground_mask_gives_the_reference_with_tied_ranges(seed: int) -> None:
    """Coordinates on a 5 cm grid: the faces of the boxes give runs of equal ranges in a
    column (the walk's ``dr > 0`` and gap tests at their edges)."""
    xyz, valid = sweep(seed, quantum_m=0.05)
    x, y = xyz[..., 0][valid], xyz[..., 1][valid]
    assert np.unique(np.hypot(x, y)).size < 0.9 * x.size  # ties there are
    assert_same_ground(xyz, valid, GroundConfig())
    assert_same_ground(xyz, valid, GroundConfig(step_m=0.0, resume_gap_m=0.0, cell_m=0.05))


@pytest.mark.parametrize("cfg", [GroundConfig(), GroundConfig(cell_m=0.3, n_sectors=7),
                                 GroundConfig(cell_m=1.1, n_sectors=360)])  # fmt: skip
def test_refine_on_the_polar_cells_boundaries(cfg: GroundConfig) -> None:
    """Returns right on ring and sector boundaries (ranges ``k * cell_m``, azimuths
    ``-pi + s * 2 pi / n_sectors``, and their neighbouring floats), where the cell of a
    return rests on the last bit of the division and of numpy's arctan2."""
    rng = np.random.default_rng(int(cfg.cell_m * 10) + cfg.n_sectors)
    H, W = 48, 512
    k = rng.integers(1, 40, (H, W))
    s = rng.integers(0, cfg.n_sectors + 1, (H, W))
    r = k * cfg.cell_m
    az = -np.pi + s * (2 * np.pi / cfg.n_sectors)
    nudge = rng.integers(-1, 2, (H, W))  # the float below, the boundary, the float above
    r = np.where(nudge < 0, np.nextafter(r, 0), np.where(nudge > 0, np.nextafter(r, 1e9), r))
    x, y = r * np.cos(az), r * np.sin(az)
    z = rng.uniform(-1.9, -1.3, (H, W))
    valid = rng.random((H, W)) < 0.9
    for ground in (rng.random((H, W)) < 0.5, rng.random((H, W)) < 0.1):
        got = refine(x, y, z, valid, ground, cfg)
        np.testing.assert_array_equal(got, refine_reference(x, y, z, valid, ground, cfg))
        assert got.any() and not got[valid].all()
    xyz = np.stack([x, y, z], axis=-1)
    assert_same_ground(xyz, valid, cfg)


# (x, y) m of returns whose sector of the default grid (180) is one by numpy's float64
# arctan2 on AVX-512 (its SIMD routine) and the next one by libm's atan2 (what a compiled
# math.atan2 calls): within a few ulps of a sector boundary, found by search on such a CPU
ATAN2_SPLIT_XY = [
    (-43.626014971585, -10.877187184872),
    (42.646391332732, 30.984416969189),
    (-31.071585857064, 30.005481677621),
    (-13.682519858391, 21.896608973673),
    (-47.149043440653, 20.992106624637),
    (-45.774893693434, 35.763266497553),
    (-27.513987166547, -23.086976483666),
    (-16.697015343033, 31.402518647936),
    (-36.43447481801, -40.464583704111),
    (-38.8986109044, 11.153997189264),
    (-16.150393130108, -7.190618300534),
    (-20.613720730879, -42.264390803764),
]


@pytest.mark.parametrize("xy", ATAN2_SPLIT_XY)
def test_sectors_follow_numpys_arctan2(xy: tuple[float, float]) -> None:
    """A return a few ulps from a sector boundary, and a much lower ground return in the
    sector across that boundary: in its own sector (numpy's) the return is its cell's lowest
    ground and stays ground; put across (another atan2's last bit) it is 0.75 m above that
    cell's lowest and is not. On any CPU the mask is the reference's."""
    cfg = GroundConfig()
    x, y = xy
    a = float(np.arctan2(y, x))
    t = (a + np.pi) * (cfg.n_sectors / (2 * np.pi))
    s_other = int(t) - 1 if t - int(t) < 0.5 else int(t) + 1
    az_other = -np.pi + (s_other + 0.5) * (2 * np.pi / cfg.n_sectors)
    r = float(np.hypot(x, y))
    xyz = np.array([[[x, y, -1.75], [r * np.cos(az_other), r * np.sin(az_other), -2.5]]])
    valid = np.ones((1, 2), dtype=bool)
    ground = assert_same_ground(xyz, valid, cfg)
    assert ground.all()
    got = refine(xyz[..., 0], xyz[..., 1], xyz[..., 2], valid, valid, cfg)
    np.testing.assert_array_equal(got, [[True, True]])
    np.testing.assert_array_equal(
        got, refine_reference(xyz[..., 0], xyz[..., 1], xyz[..., 2], valid, valid, cfg)
    )


def test_ground_mask_ignores_what_invalid_pixels_hold() -> None:
    """NaN, zero or junk in the empty pixels: the same mask and height (only valid pixels are
    read), and the reference's."""
    results = [ground_mask(*sweep(7, fill=f)) for f in ("nan", "zero", "junk")]
    for g, h in results[1:]:
        np.testing.assert_array_equal(g, results[0][0])
        assert h == results[0][1]


@pytest.mark.parametrize("height", [0.4, 1.8, 3.5])
def test_sensor_height_is_the_reference_also_when_clipped(height: float) -> None:
    """A sensor far below or above the prior: the height clips to the search range, the same
    as the reference."""
    xyz, valid = sweep(11, height=height)
    _, h = ground_mask(xyz, valid)
    z = np.where(valid, xyz[..., 2], 0.0)
    cfg = GroundConfig()
    assert h == estimate_sensor_height(z, valid, cfg)
    assert cfg.sensor_height_m - cfg.height_search_m <= h <= cfg.sensor_height_m + 1.0
    assert_same_ground(xyz, valid, cfg)


@pytest.mark.parametrize(
    "cfg",
    [
        GroundConfig(refine=False),
        GroundConfig(n_sectors=1, cell_m=0.5),
        GroundConfig(n_sectors=2, cell_m=7.0),
        GroundConfig(n_sectors=720, cell_m=0.25, max_slope_deg=10.0, step_m=0.2),
        GroundConfig(resume_gap_m=0.1, resume_gap_per_m=0.0, refine_within_m=0.5),
    ],
)
def test_ground_mask_gives_the_reference_for_other_configs(cfg: GroundConfig) -> None:
    xyz, valid = sweep(21, h=32, w=512)
    ground = assert_same_ground(xyz, valid, cfg)
    assert ground.any()


def test_ground_mask_accepts_float32_and_strided_points() -> None:
    xyz, valid = sweep(5, h=32, w=256, fill="zero")
    want = ground_mask_reference(xyz, valid)
    g32, h32 = ground_mask(xyz.astype(np.float32), valid)
    g32_ref, h32_ref = ground_mask_reference(xyz.astype(np.float32), valid)
    np.testing.assert_array_equal(g32, g32_ref)
    assert h32 == h32_ref
    # an (H, W, 3) view of a bigger array (not C-contiguous), and valid as a view too
    big = np.zeros((32, 256, 5))
    big[..., 1:4] = xyz
    strided = big[..., 1:4]
    assert not strided.flags.c_contiguous
    g, h = ground_mask(strided, np.asfortranarray(valid))
    np.testing.assert_array_equal(g, want[0])
    assert h == want[1]


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (9, 1), (3, 5), (16, 64)])
@pytest.mark.parametrize("p_valid", [0.0, 0.3, 1.0])
def test_ground_mask_on_small_and_degenerate_images(shape: tuple[int, int], p_valid) -> None:
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    xyz, _ = sweep(3, h=shape[0], w=shape[1], fill="zero")
    # valid pixels at random, with ray-cast or made-up points (a valid pixel needs a value)
    xyz = np.where(np.isfinite(xyz), xyz, rng.normal(0, 5, xyz.shape))
    valid = rng.random(shape) < p_valid
    xyz[~valid] = np.nan
    for cfg in (GroundConfig(), GroundConfig(n_sectors=1, cell_m=0.5)):
        ground = assert_same_ground(xyz, valid, cfg)
        if p_valid == 0.0:
            assert not ground.any()
            assert ground_mask(xyz, valid, cfg)[1] == cfg.sensor_height_m


def test_ground_mask_all_invalid_and_all_valid() -> None:
    xyz, valid = sweep(9)
    none = np.zeros_like(valid)
    ground, h = ground_mask(np.full_like(xyz, np.nan), none)
    assert ground.shape == valid.shape and not ground.any()
    assert h == GroundConfig().sensor_height_m
    # every pixel a return: a flat floor all round (a garage), points everywhere
    d = _rays(64, 1024, np.random.default_rng(9))
    t = np.minimum(_plane_t(d, 1.8, 0.0, 0.0), _box_t(d, np.full(3, -30.0), np.full(3, 30.0)))
    xyz_all = t[..., None] * d
    assert np.isfinite(xyz_all).all()
    all_valid = np.ones(valid.shape, dtype=bool)
    ground = assert_same_ground(xyz_all, all_valid, GroundConfig())
    assert ground[-10:].all()  # the floor under the sensor
    assert not ground[:5].any()  # the ceiling


def test_ground_mask_rejects_mismatched_shapes() -> None:
    with pytest.raises(GroundError, match="does not match"):
        ground_mask(np.zeros((4, 5, 3)), np.zeros((4, 6), dtype=bool))
    with pytest.raises(GroundError, match="does not match"):
        ground_mask(np.zeros((4, 5, 2)), np.zeros((4, 5), dtype=bool))


# ---------------------------------------------------------------- ground: the pieces


@pytest.mark.parametrize("seed", [0, 1])
def test_prepare_kernel_gives_numpys_ranges_and_lowest_returns(seed: int) -> None:
    """The compiled pass's valid coordinates, ranges (libm hypot, as numpy's) and each
    column's lowest return, against numpy's, bit for bit."""
    xyz, valid = sweep(seed)
    x_v, y_v, z_v, r_v, z_low = _prepare_kernel(xyz, valid)
    for got, k in ((x_v, 0), (y_v, 1), (z_v, 2)):
        np.testing.assert_array_equal(got, xyz[..., k][valid])
    np.testing.assert_array_equal(r_v, np.hypot(xyz[..., 0], xyz[..., 1])[valid])
    has = valid.any(axis=0)
    lowest = valid.shape[0] - 1 - np.argmax(valid[::-1], axis=0)
    cols = np.flatnonzero(has)
    np.testing.assert_array_equal(z_low, xyz[lowest[cols], cols, 2])
    assert z_low.size == has.sum() and r_v.size == valid.sum()


def test_compiled_median_height_is_numpys_to_the_bit() -> None:
    """The compiled height against numpy's median and clip: odd and even counts, ties, signed
    zeros (numpy's median of -0.0 is +0.0; its clip keeps the value on a tie with a bound),
    subnormals, infinities, and bounds that cross."""
    rng = np.random.default_rng(0)
    special = [-0.0, 0.0, 1.0, -1.0, 5e-324, -5e-324, 0.5, -2.0, np.inf, -np.inf]
    samples = [np.array(v) for v in ([-0.0], [-0.0, -0.0], [0.0, -0.0], [np.inf, -np.inf])]
    samples += [rng.choice(special, rng.integers(1, 12)) for _ in range(400)]
    samples += [rng.normal(-1.8, 0.3, n) for n in (1, 2, 999, 1000)]
    configs = [
        GroundConfig(sensor_height_m=s, height_search_m=d)
        for s, d in ((1.8, 1.0), (0.0, 0.0), (1.0, 1.0), (-1.0, 1.0), (0.0, -1.0))
    ]
    n_neg_zero = 0
    for z_low in samples:
        for cfg in configs:
            lo = cfg.sensor_height_m - cfg.height_search_m
            hi = cfg.sensor_height_m + cfg.height_search_m
            got = _median_height(z_low, float(cfg.sensor_height_m), float(lo), float(hi))
            want = _height_from_lowest(z_low, cfg)
            if np.isnan(want):
                assert np.isnan(got)
                continue
            assert got == want and np.signbit(got) == np.signbit(want), (z_low, cfg)
            n_neg_zero += want == 0 and np.signbit(want)
    assert n_neg_zero > 0  # the sign of a zero was tested both ways
    assert _median_height(np.zeros(0), 1.8, 0.8, 2.8) == 1.8


def test_hypot_matches_numpy_on_awkward_values() -> None:
    """Ranges over many magnitudes, signed zeros, subnormals and infinities."""
    rng = np.random.default_rng(0)
    vals = np.concatenate(
        [
            rng.normal(0, 1, 4000) * 10.0 ** rng.uniform(-300, 300, 4000),
            [0.0, -0.0, 5e-324, -5e-324, 1e308, -1e308, np.inf, -np.inf, 3.0, 4.0],
        ]
    )
    xyz = np.stack([vals, rng.permutation(vals), np.zeros_like(vals)], axis=-1)[None]
    valid = np.ones(xyz.shape[:2], dtype=bool)
    _, _, _, r_v, _ = _prepare_kernel(np.ascontiguousarray(xyz), valid)
    np.testing.assert_array_equal(r_v, np.hypot(xyz[0, :, 0], xyz[0, :, 1]))


@pytest.mark.parametrize("fill", ["nan", "zero"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_column_walk_and_refine_give_the_references(seed: int, fill: str) -> None:
    """The public wrappers of the kernels on image-sized arrays, NaN or zero where empty."""
    xyz, valid = sweep(seed, fill=fill)
    x, y, z = (xyz[..., k] for k in range(3))
    r = np.hypot(x, y)
    cfg = GroundConfig()
    for h in (1.2, 1.8, 2.5):
        walk = column_walk(r, z, valid, h, cfg)
        # the reference on zero-filled arrays (a NaN would carry through its row arithmetic)
        r0, z0 = np.where(valid, r, 0.0), np.where(valid, z, 0.0)
        np.testing.assert_array_equal(walk, column_walk_reference(r0, z0, valid, h, cfg))
    assert walk.any()
    rng = np.random.default_rng(seed)
    for ground in (walk, rng.random(valid.shape) < 0.5, np.zeros_like(valid), valid):
        got = refine(x, y, z, valid, ground, cfg)
        np.testing.assert_array_equal(got, refine_reference(x, y, z, valid, ground, cfg))
        np.testing.assert_array_equal(got, refine(x, y, z, valid, ground, cfg, r_m=r))
        assert not (got & ~valid).any()


# ---------------------------------------------------------------- windowing


def _windows(seed: int, n: int, H: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n window centres (sensor frame, m) around the sensor, sigmas, and the rows' elevations
    (a few rows NaN, as rows without returns)."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(-np.pi, np.pi, n)
    # some right on the azimuth seam, where the window wraps
    az[: n // 5] = rng.choice([-np.pi, np.pi], n // 5) + rng.normal(0, 0.01, n // 5)
    rg = rng.uniform(0.5, 80.0, n)
    c = np.stack([rg * np.cos(az), rg * np.sin(az), rng.uniform(-3.0, 2.0, n)], axis=1)
    sigma = rng.exponential(0.5, n)
    sigma[: n // 7] = 50.0  # clamped to max_half_m; near ones span the whole row
    row_el = np.linspace(0.3, -0.4, H)
    row_el[rng.random(H) < 0.1] = np.nan
    return c, sigma, row_el


@pytest.mark.parametrize("n", [1, 11, 265, 2000])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_window_mask_gives_the_reference(seed: int, n: int) -> None:
    c, sigma, row_el = _windows(seed, n)
    for shape, cfg in (((64, 1024), None), ((64, 360), WindowConfig(1.0, 1.0, 3.0))):
        got = window_mask(shape, c, sigma, row_el, cfg)
        want = window_mask_reference(shape, c, sigma, row_el, cfg)
        assert got.dtype == np.bool_ and got.shape == shape
        np.testing.assert_array_equal(got, want)
        assert got.any() and not got.all()
        assert not got[~np.isfinite(row_el)].any()


def test_window_mask_wraps_in_azimuth() -> None:
    """A window straddling azimuth pi covers both ends of its rows, not the middle."""
    c = np.array([[-20.0, 0.0, -1.8]])
    row_el = np.linspace(0.3, -0.4, 64)
    got = window_mask((64, 1024), c, np.array([0.5]), row_el)
    np.testing.assert_array_equal(got, window_mask_reference((64, 1024), c, [0.5], row_el))
    rows = np.flatnonzero(got.any(axis=1))
    assert rows.size > 0
    assert got[rows, 0].all() and got[rows, -1].all() and not got[rows, 512].any()


def test_window_mask_degenerate_windows() -> None:
    """No windows, no rows with returns, windows at the sensor or missing every row, negative
    and NaN sigmas (empty or reversed intervals), one column: the reference's masks."""
    row_el = np.linspace(0.3, -0.4, 16)
    rng = np.random.default_rng(3)
    c = rng.normal(0, 10, (40, 3))
    c[0] = 0.0  # at the sensor
    c[1] = [5.0, 0.0, 500.0]  # straight up: above every row
    sigma = rng.normal(0, 2.0, 40)  # some negative: windows narrower than one column
    sigma[2] = np.nan
    cases = [
        ((16, 90), np.zeros((0, 3)), np.zeros(0), row_el),
        ((16, 90), c, sigma, np.full(16, np.nan)),
        ((16, 90), c, sigma, row_el),
        ((16, 90), c, np.full(40, -1.0), row_el),
        ((16, 1), c, sigma, row_el),
        ((1, 90), c, sigma, row_el[:1]),
    ]
    for shape, cc, ss, re in cases:
        got = window_mask(shape, cc, ss, re)
        np.testing.assert_array_equal(got, window_mask_reference(shape, cc, ss, re))
        assert got.shape == shape
    # windows of negative width (sigma below -base/k): reversed intervals, some starting at
    # column 0 (so ending at -1, which both index from the end), still within their rows
    row_el64 = np.linspace(0.3, -0.4, 64)
    az = np.pi - (np.arange(0, 1024, 37) + 0.5) * 2 * np.pi / 1024
    az[0] = -np.pi + 1e-9  # the last column: its reversed interval starts at 0, ends at -1
    el = row_el64[np.arange(az.size) % 64]
    c_rev = 10.0 * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    s_rev = np.full(az.size, (-0.08 - 1.0) / 3.0)  # half-width -0.08 m at 10 m: -1.3 columns
    s_rev[1::2] = 0.5
    got = window_mask((64, 1024), c_rev, s_rev, row_el64)
    np.testing.assert_array_equal(got, window_mask_reference((64, 1024), c_rev, s_rev, row_el64))
    assert got.any()
    assert not window_mask((16, 90), c, sigma, np.full(16, np.nan)).any()
    assert window_mask((16, 90), c, sigma, row_el).any()
    with pytest.raises(WindowingError, match="sigmas"):
        window_mask((16, 90), c, sigma[:3], row_el)
