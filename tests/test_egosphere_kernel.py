"""The compiled egosphere projection (sp.egosphere.to_egosphere) gives the numpy reference's
image (to_egosphere_reference) bit for bit: the same point in every pixel and layer, the same
ranges (and the same NaN where a pixel is empty), the same drop and overflow counts."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from kernel_reference.egosphere_reference import to_egosphere_reference

from logs.types import LadarScan
from sp.egosphere import EgosphereConfig, EgosphereImage, to_egosphere

# the reference casts NaN angles of dropped points to int32
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered in cast:RuntimeWarning")


def scan_of(points: np.ndarray, ring: np.ndarray | None = None) -> LadarScan:
    n = len(points)
    return LadarScan(
        t_ns=1_000_000_000,
        frame_id="ladar",
        points_xyz=np.asarray(points, np.float32),
        intensity=np.linspace(0, 1, n, dtype=np.float32),
        t_offset_ns=np.arange(n, dtype=np.int64) * 1000,
        ring=ring,
    )


def random_scan(seed: int, n: int, with_ring: bool, sweep_order: bool = False) -> LadarScan:
    """n points (a little more: duplicates are appended) over and beyond the default
    elevation span, some NaN, some nearer than 0.5 m, some on bin edges, many tied in range."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.radians(rng.uniform(-30.0, 8.0, n))  # default span -25..3 deg: some dropped
    # some points on column and row edges of the 64 x 1024 and 48 x 100 grids
    edge = rng.random(n) < 0.1
    cols = rng.choice([1024, 100], n)
    az[edge] = np.pi - rng.integers(0, cols[edge] + 1) * (2 * np.pi / cols[edge])
    edge_el = rng.random(n) < 0.05
    el[edge_el] = np.radians(3.0 - rng.integers(0, 65, int(edge_el.sum())) * 28.0 / 64)
    r = rng.uniform(0.0, 80.0, n)
    r[rng.random(n) < 0.1] = rng.choice([10.0, 20.0])  # the same range from many directions
    xyz = np.column_stack(
        [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
    ).astype(np.float32)
    xyz[rng.random(n) < 0.03, rng.integers(0, 3)] = np.nan
    # straight behind, on either side of the azimuth seam (atan2 of -0 and +0: -pi and pi)
    xyz[:4] = [[-5.0, 0.0, -1.0], [-5.0, -0.0, -1.0], [-7.0, 0.0, -1.0], [-7.0, -0.0, -1.0]]
    ring = rng.integers(0, 70, n).astype(np.uint16) if with_ring else None  # >= 64: dropped
    # exact duplicates and z-mirrored copies (the same range, the same pixel when the row is
    # the beam): ties in range, broken by the point index
    dup = rng.choice(n, n // 10)
    mirrored = xyz[dup] * np.float32([1.0, 1.0, -1.0])
    xyz = np.concatenate([xyz, xyz[dup], mirrored])
    if ring is not None:
        ring = np.concatenate([ring, ring[dup], ring[dup]])
    if sweep_order:  # column by column, as a spinning LADAR fires
        order = np.argsort(-np.arctan2(xyz[:, 1], xyz[:, 0]), kind="stable")
        xyz = xyz[order]
        ring = None if ring is None else ring[order]
    return scan_of(xyz, ring)


def assert_same_image(scan: LadarScan, cfg: EgosphereConfig) -> EgosphereImage:
    got = to_egosphere(scan, cfg)
    want = to_egosphere_reference(scan, cfg)
    shape = (cfg.n_rows, cfg.n_cols, cfg.max_returns)
    assert got.point_index.shape == want.point_index.shape == shape
    assert got.point_index.dtype == np.int32 and got.range_m.dtype == np.float32
    # the same memory layout (the reference's (K, rows, cols) arrays seen as (rows, cols, K))
    assert got.point_index.strides == want.point_index.strides
    assert got.range_m.strides == want.range_m.strides
    np.testing.assert_array_equal(got.point_index, want.point_index)
    np.testing.assert_array_equal(np.isnan(got.range_m), np.isnan(want.range_m))
    np.testing.assert_array_equal(got.range_m, want.range_m)
    # bit for bit, the NaN of an empty pixel too (the reference's is the all-ones key's half,
    # or np.nan in the layers it did not need to compute)
    np.testing.assert_array_equal(got.range_m.view(np.uint32), want.range_m.view(np.uint32))
    assert (got.n_dropped, got.n_overflow) == (want.n_dropped, want.n_overflow)
    assert got.n_dropped + got.n_overflow + int(got.valid.sum()) == scan.n_points
    return got


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("n", [1_000, 20_000, 70_000])
@pytest.mark.parametrize("with_ring", [True, False])
@pytest.mark.parametrize("max_returns", [1, 2, 3])
def test_kernel_gives_the_reference_image(seed, n, with_ring, max_returns):
    scan = random_scan(seed, n, with_ring, sweep_order=seed == 1)
    cfg = EgosphereConfig(n_rows=64, n_cols=1024, max_returns=max_returns)
    img = assert_same_image(scan, cfg)
    assert img.n_dropped > 0  # NaN, near and out-of-span points were all there
    assert img.valid[..., 0].any()
    if n == 70_000:  # several points per pixel: later layers and overflow exercised
        assert img.valid[..., -1].any() and img.n_overflow > 0


@pytest.mark.parametrize("seed", range(2))
@pytest.mark.parametrize(
    "cfg",
    [
        EgosphereConfig(n_rows=48, n_cols=100, max_returns=3),
        EgosphereConfig(n_rows=48, n_cols=100, max_returns=2, use_ring=False),
        EgosphereConfig(n_rows=64, n_cols=2048, ring_zero_at_bottom=False),
        # 0.7 m rounds down in float32: the reference keeps a range of float32(0.7)
        EgosphereConfig(n_rows=16, n_cols=333, max_returns=1, min_range_m=0.7),
        EgosphereConfig(elevation_min_deg=-90.0, elevation_max_deg=90.0, max_returns=4),
    ],
    ids=["100-cols", "no-ring-rows", "ring-zero-at-top", "min-range-0.7", "full-span"],
)
def test_kernel_gives_the_reference_image_for_other_grids(seed, cfg):
    for with_ring in (True, False):
        img = assert_same_image(random_scan(10 + seed, 30_000, with_ring), cfg)
        assert img.valid.any()


def test_a_point_at_min_range_is_kept_as_numpy_compares_it():
    # numpy compares the float32 ranges with float32(min_range_m), which for 0.7 is below 0.7
    r = np.float32(0.7)
    below = np.nextafter(r, np.float32(0))
    assert float(below) < float(r) < 0.7
    scan = scan_of(np.array([[r, 0.0, 0.0], [below, 0.0, 0.0]]))
    assert np.linalg.norm(scan.points_xyz, axis=1).tolist() == [r, below]
    cfg = EgosphereConfig(n_rows=4, n_cols=8, max_returns=1, min_range_m=0.7)
    img = assert_same_image(scan, cfg)
    assert img.point_index[img.valid].tolist() == [0] and img.n_dropped == 1


@pytest.mark.parametrize("max_returns", [1, 2, 3])
def test_ties_in_range_go_to_the_lower_index(max_returns):
    # Four copies of one point and its mirror in z on one beam: one pixel, one range.
    p = [12.0, 3.0, -0.5]
    pts = np.array([p, p, [12.0, 3.0, 0.5], p, [30.0, 7.5, -1.25]], np.float32)
    ring = np.full(len(pts), 5, np.uint16)
    cfg = EgosphereConfig(n_rows=8, n_cols=16, max_returns=max_returns)
    img = assert_same_image(scan_of(pts, ring), cfg)
    rows, cols = np.nonzero(img.valid[..., 0])
    assert len(rows) == 1
    assert img.point_index[rows[0], cols[0]].tolist() == [0, 1, 2][:max_returns]
    assert img.n_overflow == len(pts) - max_returns


@pytest.mark.parametrize("with_ring", [True, False])
@pytest.mark.parametrize("max_returns", [1, 2, 3])
def test_empty_and_all_dropped_scans(with_ring, max_returns):
    cfg = EgosphereConfig(n_rows=8, n_cols=32, max_returns=max_returns)
    empty = scan_of(np.zeros((0, 3)), np.zeros(0, np.uint16) if with_ring else None)
    img = assert_same_image(empty, cfg)
    assert not img.valid.any() and np.isnan(img.range_m).all()
    assert img.n_dropped == 0 and img.n_overflow == 0
    pts = np.array([[np.nan, 1.0, 0.0], [0.1, 0.0, 0.0], [5.0, 0.0, 0.0]], np.float32)
    ring = np.array([0, 1, 99], np.uint16) if with_ring else None  # the last out of the beams
    if not with_ring:
        pts[2] = [5.0, 0.0, 4.0]  # 38 degrees up, above the elevation span
    img = assert_same_image(scan_of(pts, ring), cfg)
    assert not img.valid.any() and img.n_dropped == 3


@pytest.mark.parametrize("ring_dtype", [np.int64, np.int32, np.uint8, np.float32])
def test_other_ring_dtypes_are_read_as_the_reference_reads_them(ring_dtype):
    scan = random_scan(7, 5_000, with_ring=True)
    scan.ring = scan.ring.astype(ring_dtype)
    img = assert_same_image(scan, EgosphereConfig(n_rows=64, n_cols=512, max_returns=2))
    assert img.valid.any()


def test_a_strided_sweep_gives_the_reference_image():
    # KITTI-like (N, 4) records whose first three columns are the points: a strided view
    scan = random_scan(3, 10_000, with_ring=False)
    records = np.concatenate([scan.points_xyz, scan.intensity[:, None]], axis=1)
    scan.points_xyz = records[:, :3]
    assert not scan.points_xyz.flags.c_contiguous
    img = assert_same_image(scan, EgosphereConfig(max_returns=2))
    assert img.valid.any()


def test_work_arrays_reused_across_sweeps_and_threads_leave_no_trace():
    # to_egosphere keeps its work arrays between calls (one set per thread): a large sweep,
    # a small one with more layers, then the large one again must each give their own image.
    big, small = random_scan(20, 40_000, True), random_scan(21, 2_000, False)
    cfg1 = EgosphereConfig(n_rows=64, n_cols=1024, max_returns=1)
    cfg3 = EgosphereConfig(n_rows=16, n_cols=128, max_returns=3)
    first = assert_same_image(big, cfg1)
    assert_same_image(small, cfg3)
    again = assert_same_image(big, cfg1)
    np.testing.assert_array_equal(first.point_index, again.point_index)

    def project(scan: LadarScan, cfg: EgosphereConfig) -> list[np.ndarray]:
        return [to_egosphere(scan, cfg).point_index for _ in range(50)]

    with ThreadPoolExecutor(max_workers=2) as pool:  # the kernels release the GIL
        runs = [pool.submit(project, big, cfg1), pool.submit(project, small, cfg3)]
        got = [r.result() for r in runs]
    for images, (scan, cfg) in zip(got, [(big, cfg1), (small, cfg3)], strict=True):
        want = to_egosphere_reference(scan, cfg).point_index
        for image in images:
            np.testing.assert_array_equal(image, want)
