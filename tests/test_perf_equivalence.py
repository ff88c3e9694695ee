"""The fast paths of maps.pyramid give what the plain definitions give (maps.fusion's are held
to its slow point-by-point reference in test_maps_fusion.py, unchanged).

Window sums (summed-area tables for small regions, row/column reductions for large
ones) against direct float64 sums; the correlation surface against normalised correlation
computed directly in float64; attributes far from zero (ranges of 50 m varying by
millimetres) register as well as the same attribute near zero.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from maps.pyramid import TABLE_MAX_PX, _window_sums, register


def _direct_window_sums(region: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, ...]:
    h, w = shape
    k = region.shape[0] - h + 1
    r = region.astype(np.float64)
    s = np.array([[r[a : a + h, b : b + w].sum() for b in range(k)] for a in range(k)])
    ss = np.array([[(r[a : a + h, b : b + w] ** 2).sum() for b in range(k)] for a in range(k)])
    return s, ss


@pytest.mark.parametrize(
    "region_shape, k",
    [((10, 12), 5), ((5, 6), 5), ((3, 3), 3), ((7, 9), 1), ((140, 130), 3), ((300, 280), 5)],
)
def test_window_sums_equal_direct_sums(region_shape, k):
    rng = np.random.default_rng(k + region_shape[0])
    region = (50.0 + rng.random(region_shape)).astype(np.float32)  # far from zero
    shape = (region_shape[0] - k + 1, region_shape[1] - k + 1)
    s, ss = _window_sums(region, shape)
    want_s, want_ss = _direct_window_sums(region, shape)
    np.testing.assert_allclose(s, want_s, rtol=1e-13)
    np.testing.assert_allclose(ss, want_ss, rtol=1e-13)


def test_both_window_sum_paths_are_exercised():
    assert 10 * 12 <= TABLE_MAX_PX < 300 * 280


def _texture(shape: tuple[int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 2.0)


def _direct_ncc(ref: np.ndarray, mov: np.ndarray, center: tuple[int, int], d: tuple[int, int]):
    """Normalised correlation (float64) of ``mov`` against ``ref`` moved by ``center + d``,
    over the window the search builds at ``center``: the pixels of ``mov`` whose partners in
    ``ref`` exist for every offset within 2 px of ``center``."""
    (cr, cc), reach = center, 2
    h, w = mov.shape
    r0, r1 = max(0, cr + reach), min(h, ref.shape[0] + cr - reach)
    c0, c1 = max(0, cc + reach), min(w, ref.shape[1] + cc - reach)
    dr, dc = cr + d[0], cc + d[1]
    a = mov[r0:r1, c0:c1].astype(np.float64)
    b = ref[r0 - dr : r1 - dr, c0 - dc : c1 - dc].astype(np.float64)
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


@pytest.mark.parametrize("size", [48, 128, 256])  # eager, lazy with tables, lazy with reductions
def test_surface_is_the_normalised_correlation_around_the_peak(size):
    """One level, starting at the true offset: the window is built there and the surface holds
    the normalised correlations at the 9 offsets around it."""
    big = _texture((size + 60, size + 60), size)
    shift = (6, -4)
    ref = big[30 : 30 + size, 30 : 30 + size]
    mov = big[30 - shift[0] : 30 + size - shift[0], 30 - shift[1] : 30 + size - shift[1]]
    m = register(ref, mov, levels=1, initial_shift_rc=shift)
    want = [[_direct_ncc(ref, mov, shift, (i, j)) for j in (-1, 0, 1)] for i in (-1, 0, 1)]
    np.testing.assert_allclose(m.surface, want, atol=1e-5)
    assert np.abs(m.shift_rc - shift).max() < 0.02  # the parabola through the peak


@pytest.mark.parametrize("offset", [0.0, 50.0, 1000.0])
def test_registration_does_not_depend_on_the_attribute_offset(offset):
    """A range-like image (tens of metres varying by millimetres) registers like the same
    image near zero: the correlation sums keep their precision after the mean comes out."""
    big = _texture((320, 320), 7) * np.float32(0.01)  # a few millimetres of relief
    shift = (9, -13)
    ref = big[32:288, 32:288] + np.float32(offset)
    mov = big[32 - shift[0] : 288 - shift[0], 32 - shift[1] : 288 - shift[1]] + np.float32(offset)
    m = register(ref, mov, max_shift_px=16)
    assert np.abs(m.shift_rc - shift).max() < 0.05
    assert 0.99 < m.peak <= 1.0 + 1e-6
    assert m.confidence > 0.7


# --- sp.ground: the compiled kernels against their numpy references (the same masks) ------


def _ground_scene(seed: int, h: int = 64, w: int = 256, p_invalid: float = 0.1):
    """A LADAR-like egosphere (sensor 1.8 m up, beams from +0.3 to -0.4 rad) with noise,
    raised returns (objects) and holes; x, y, z zero where invalid, as ground_mask gives."""
    rng = np.random.default_rng(seed)
    el = np.linspace(0.3, -0.4, h)[:, None]
    az = np.linspace(-np.pi, np.pi, w, endpoint=False)[None]
    rng_m = np.minimum(1.8 / np.maximum(np.tan(-el), 0.02), 80.0)
    rng_m = rng_m * (1 + 0.05 * rng.standard_normal((h, w)))
    z = rng_m * np.tan(el) + 0.05 * rng.standard_normal((h, w))
    z[rng.random((h, w)) < 0.05] += rng.uniform(0.1, 2.0)
    valid = rng.random((h, w)) >= p_invalid
    x, y = rng_m * np.cos(az), rng_m * np.sin(az)
    return (*(np.where(valid, a, 0.0) for a in (x, y, z)), valid)


@pytest.mark.parametrize("seed, p_invalid", [(0, 0.1), (1, 0.0), (2, 0.6), (3, 1.0)])
def test_ground_kernels_give_the_reference_masks(seed, p_invalid):
    from sp.ground import GroundConfig, column_walk, column_walk_reference, refine, refine_reference

    cfg = GroundConfig()
    x, y, z, valid = _ground_scene(seed, p_invalid=p_invalid)
    r = np.hypot(x, y)
    for h in (1.2, 1.8, 2.5):
        walk = column_walk(r, z, valid, h, cfg)
        np.testing.assert_array_equal(walk, column_walk_reference(r, z, valid, h, cfg))
    assert p_invalid == 1.0 or walk.any()
    rng = np.random.default_rng(seed)
    for ground in (walk, rng.random(valid.shape) < 0.5, np.zeros_like(valid), valid):
        got = refine(x, y, z, valid, ground, cfg)
        np.testing.assert_array_equal(got, refine_reference(x, y, z, valid, ground, cfg))
        np.testing.assert_array_equal(got, refine(x, y, z, valid, ground, cfg, r_m=r))


@pytest.mark.filterwarnings("ignore:invalid value encountered")
def test_ground_kernels_on_degenerate_images():
    from sp.ground import GroundConfig, column_walk, column_walk_reference, refine, refine_reference

    cfg = GroundConfig(n_sectors=1, cell_m=0.5)
    for shape in ((1, 1), (1, 7), (9, 1)):
        x, y, z, valid = (a[: shape[0], : shape[1]] for a in _ground_scene(5, 9, 7, 0.2))
        z = z.copy()
        z[0, 0] = np.nan  # a NaN return that claims to be valid
        walk = column_walk(np.hypot(x, y), z, valid, 1.8, cfg)
        np.testing.assert_array_equal(
            walk, column_walk_reference(np.hypot(x, y), z, valid, 1.8, cfg)
        )
        for ground in (walk, valid, ~valid):
            np.testing.assert_array_equal(
                refine(x, y, z, valid, ground, cfg), refine_reference(x, y, z, valid, ground, cfg)
            )


@pytest.mark.parametrize("seed, p_ground", [(0, 0.5), (1, 0.05), (2, 1.0), (3, 0.0)])
def test_ground_below_kernel_gives_the_reference_heights(seed, p_ground):
    from sp.computation import ground_below, ground_below_reference

    rng = np.random.default_rng(seed)
    shape = (64, 300)
    ground = rng.random(shape) < p_ground
    z = rng.normal(0.0, 2.0, shape)
    r = np.abs(rng.normal(20.0, 15.0, shape))
    r[rng.random(shape) < 0.05] = np.nan  # empty pixels
    z[rng.random(shape) < 0.02] = np.nan
    for r_m in (None, r):
        for slope, reach in ((0.3, 15.0), (0.0, 1.0), (2.0, 100.0)):
            got = ground_below(ground, z, r_m, slope, reach)
            want = ground_below_reference(ground, z, r_m, slope, reach)
            np.testing.assert_array_equal(got, want)
    assert p_ground == 0.0 or np.isfinite(got).any()


def test_ground_below_on_degenerate_images():
    from sp.computation import ComputationError, ground_below, ground_below_reference

    for shape in ((1, 1), (1, 5), (6, 1)):
        ground = np.ones(shape, dtype=bool)
        z, r = np.arange(np.prod(shape), dtype=float).reshape(shape), np.ones(shape)
        np.testing.assert_array_equal(
            ground_below(ground, z, r), ground_below_reference(ground, z, r)
        )
    with pytest.raises(ComputationError, match=r"r_m \(2, 2\)"):
        ground_below(np.ones((3, 3), bool), np.zeros((3, 3)), np.zeros((2, 2)))


# --- kd_store.covariance: the compiled PSD test against the unrolled numpy factorisation -----


def _covariances(n: int, seed: int) -> np.ndarray:
    """(n, 6, 6): PSD, rank-deficient (PSD by the tolerance or not), indefinite, zero, NaN,
    inf and huge matrices mixed."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 6, 6))
    A[1::4, :, 3:] = 0.0  # rank 3
    C = A @ A.transpose(0, 2, 1)
    C[2::5] -= np.eye(6) * rng.uniform(1e-12, 1.0, (len(C[2::5]), 1, 1))  # some indefinite
    C[3::11] = 0.0
    C[4::13, 1, 1] = np.nan
    C[5::17, 0, 5] = C[5::17, 5, 0] = np.inf
    C[6::19] *= 1e150
    return C


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the reference on inf and 1e150
@pytest.mark.parametrize("n, seed", [(0, 0), (1, 1), (3, 2), (500, 3), (20_000, 4)])
def test_psd_kernel_gives_the_reference_answers(n, seed):
    from kd_store.covariance import pack_covariance, psd_mask, psd_mask_reference

    cov21 = pack_covariance(_covariances(n, seed))
    for tol in (1e-9, 0.0, 1e-3):
        got = psd_mask(cov21, tol)
        np.testing.assert_array_equal(got, psd_mask_reference(cov21, tol))
        scale = np.full(n, 7.0)
        np.testing.assert_array_equal(
            psd_mask(cov21, tol, scale), psd_mask_reference(cov21, tol, scale)
        )
    if n >= 500:
        assert 0 < got.sum() < n  # both answers occur


def test_psd_kernel_refuses_a_wrong_shape():
    from kd_store import KDError
    from kd_store.covariance import psd_mask

    with pytest.raises(KDError, match=r"\(4, 6\)"):
        psd_mask(np.zeros((4, 6)))


def _random_sweep(seed: int, p_invalid: float):
    """A random 16 x 64 sweep (some beams empty, NaN where no return) as an egosphere image,
    with a random sensor pose and per-column poses."""
    from core.geometry import interpolate_pose, rotvec_to_matrix, se3
    from logs.types import LadarScan
    from sp.egosphere import EgosphereConfig, to_egosphere

    rng = np.random.default_rng(seed)
    n = 16 * 64
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.radians(rng.uniform(-14.0, 14.0, n))
    r = rng.uniform(1.0, 80.0, n)
    xyz = np.column_stack(
        [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
    )
    keep = rng.random(n) >= p_invalid
    scan = LadarScan(
        1_000_000_000, "ladar", xyz[keep].astype(np.float32), np.ones(int(keep.sum()), np.float32),
        rng.integers(0, 100_000_000, int(keep.sum())).astype(np.int64),
    )  # fmt: skip
    img = to_egosphere(scan, EgosphereConfig(n_rows=16, n_cols=64))
    rot = rng.normal(0, 0.3, 3)
    T = se3(rotvec_to_matrix(rot), rng.normal(0, 50, 3))
    T_prev = se3(rotvec_to_matrix(rot + rng.normal(0, 0.05, 3)), T[:3, 3] - rng.normal(0, 1, 3))
    T_cols = interpolate_pose(T_prev, T, rng.uniform(0.5, 1.5, img.valid_first.shape[1]))
    return img, T, T_cols


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("p_invalid", [0.0, 0.4, 1.0])
@pytest.mark.parametrize("per_column", [False, True])
def test_sweep_points_kernel_gives_the_reference_points(seed, p_invalid, per_column):
    from sp.sweep_points import sweep_points, sweep_points_reference

    img, T, T_cols = _random_sweep(seed, p_invalid)
    poses = T_cols if per_column else T[None]
    got = sweep_points(img, T[:3, :3], poses)
    want = sweep_points_reference(img, T[:3, :3], poses)
    for name, g, w in zip(("xyz_s", "xyz_g", "xyz_w", "row_el"), got, want, strict=True):
        assert g.shape == w.shape, name
        np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-9, err_msg=name)
        assert np.array_equal(np.isnan(g), np.isnan(w)), name
    if p_invalid == 1.0:
        assert np.isnan(got[3]).all() and not got[0].any()


def test_sweep_points_refuses_poses_of_the_wrong_shape():
    from sp.sweep_points import sweep_points

    img, T, _ = _random_sweep(0, 0.2)
    with pytest.raises(ValueError, match=r"T_world_cols has shape \(3, 4, 4\)"):
        sweep_points(img, T[:3, :3], np.stack([T] * 3))


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("p_ground", [0.0005, 0.3, 1.0])
def test_ground_plane_sums_give_the_reference_plane(seed, p_ground):
    """The compiled sums of the ground plane fit give the reference's plane, roughness and
    count (a tilted noisy plane 60 m wide, far from the origin), and None under 10 points."""
    from sp.computation import ground_plane, ground_plane_reference

    rng = np.random.default_rng(seed)
    centre = np.array([1000.0, -2000.0, 51.9])
    xy = centre[:2] + rng.uniform(-30, 30, (64, 128, 2))
    z = (
        50.0
        + 0.05 * (xy[..., 0] - 1000)
        - 0.02 * (xy[..., 1] + 2000)
        + rng.normal(0, 0.03, xy.shape[:2])
    )
    xyz = np.dstack([xy, z])
    ground = rng.random((64, 128)) < p_ground
    got, want = (
        ground_plane(xyz, ground, centre, 20.0),
        ground_plane_reference(xyz, ground, centre, 20.0),
    )
    if want is None:
        assert got is None
        return
    assert got is not None and got[2] == want[2] > 10
    np.testing.assert_allclose(got[0], want[0], rtol=1e-9, atol=1e-12)
    assert got[1] == pytest.approx(want[1], rel=1e-6)
    np.testing.assert_allclose(got[0][:2], [0.05, -0.02], atol=0.01)  # the plane it is
    assert got[1] == pytest.approx(0.03, rel=0.2)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("order", ["firing", "shuffled"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_deskew_kernel_gives_the_reference_points(seed, order, dtype):
    """Sweep points moved to the world slice by slice: the compiled pass and the numpy form
    agree (points in firing order or not, float32 or float64 input), and a point at the
    start and one at the end of the sweep move with the first and last slice's pose."""
    from core.geometry import interpolate_pose, rotvec_to_matrix, se3, transform_points
    from wm.poses import PoseTrack, deskew_to_world, deskew_to_world_reference

    rng = np.random.default_rng(seed)
    track = PoseTrack()
    T0 = se3(rotvec_to_matrix(rng.normal(0, 0.5, 3)), rng.normal(0, 100, 3))
    T1 = T0 @ se3(rotvec_to_matrix([0, 0, 0.2]), [1.5, 0.1, 0.0])
    track.add(0, T0)
    track.add(100_000_000, T1)
    T_body_sensor = se3(rotvec_to_matrix([0.0, 0.05, 0.0]), [0.3, 0.0, 1.9])
    n = 5000
    off = np.sort(rng.integers(0, 100_000_000, n))
    off[0], off[-1] = 0, 99_999_999
    if order == "shuffled":
        off = rng.permutation(off)
    pts = rng.uniform(-60, 60, (n, 3)).astype(dtype)
    got = deskew_to_world(pts, off, 0, track, T_body_sensor, 8)
    want = deskew_to_world_reference(pts, off, 0, track, T_body_sensor, 8)
    assert got.dtype == np.float64 and got.shape == (n, 3)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    span = int(off.max())
    for i, b in ((int(np.argmin(off)), 0), (int(np.argmax(off)), 7)):
        T = interpolate_pose(T0, T1, (b + 0.5) / 8 * span / 100_000_000) @ T_body_sensor
        np.testing.assert_allclose(got[i], transform_points(T, pts[i : i + 1].astype(float))[0])


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("voxel_m", [0.05, 0.5, 3.0])
def test_voxel_thinning_gives_the_reference_points(seed, voxel_m):
    """The first point of each voxel, found by the compiled hash, is the numpy reference's, and
    it is KISS-ICP's down-sampling of the same points (the same set of points kept)."""
    from kiss_icp.voxelization import voxel_down_sample

    from sp.voxels import first_per_voxel, first_per_voxel_reference

    rng = np.random.default_rng(seed)
    pts = np.concatenate([rng.normal(0, 10, (4000, 3)), rng.uniform(-3, 3, (4000, 3))])
    pts[::7] = pts[1::7][: len(pts[::7])]  # repeats: later copies are never kept
    got = first_per_voxel(pts, voxel_m)
    assert np.array_equal(got, first_per_voxel_reference(pts, voxel_m))
    assert np.all(np.diff(got) > 0)
    keys = np.floor(pts / voxel_m)
    assert len(np.unique(keys[got], axis=0)) == len(got) == len(np.unique(keys, axis=0))
    kiss = voxel_down_sample(pts, voxel_m)
    assert {tuple(p) for p in np.asarray(kiss)} == {tuple(p) for p in pts[got]}


def test_voxel_thinning_refuses_bad_input():
    from sp.voxels import VoxelError, first_per_voxel

    with pytest.raises(VoxelError, match="voxel_m must be positive, got 0"):
        first_per_voxel(np.zeros((3, 3)), 0.0)
    with pytest.raises(VoxelError, match=r"got shape \(3, 2\)"):
        first_per_voxel(np.zeros((3, 2)), 1.0)
    with pytest.raises(VoxelError, match="NaN or inf"):
        first_per_voxel(np.array([[0.0, np.nan, 0.0]]), 1.0)
    assert first_per_voxel(np.zeros((0, 3)), 1.0).shape == (0,)
