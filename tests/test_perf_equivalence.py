"""The fast paths of maps.pyramid give what the plain definitions give (maps.fusion's are held
to its slow point-by-point reference in test_maps_fusion.py, unchanged), and the argument checks
of compiled kernels (their equivalence to the numpy oracles is test_kernel_equivalence.py).

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


# --- argument checks of compiled kernels ---------------------------------------------------


def test_ground_below_names_mismatched_shapes():
    from sp.computation import ComputationError, ground_below

    with pytest.raises(ComputationError, match=r"r_m \(2, 2\)"):
        ground_below(np.ones((3, 3), bool), np.zeros((3, 3)), np.zeros((2, 2)))


def test_psd_kernel_refuses_a_wrong_shape():
    from kd_store import KDError
    from kd_store.covariance import psd_mask

    with pytest.raises(KDError, match=r"\(4, 6\)"):
        psd_mask(np.zeros((4, 6)))


def test_sweep_points_refuses_poses_of_the_wrong_shape():
    from sp.sweep_points import sweep_points
    from tests.test_kernel_equivalence import _random_sweep

    img, T, _ = _random_sweep(0, 0.2)
    with pytest.raises(ValueError, match=r"T_world_cols has shape \(3, 4, 4\)"):
        sweep_points(img, T[:3, :3], np.stack([T] * 3))


def test_voxel_thinning_refuses_bad_input():
    from sp.voxels import VoxelError, first_per_voxel

    with pytest.raises(VoxelError, match="voxel_m must be positive, got 0"):
        first_per_voxel(np.zeros((3, 3)), 0.0)
    with pytest.raises(VoxelError, match=r"got shape \(3, 2\)"):
        first_per_voxel(np.zeros((3, 2)), 1.0)
    with pytest.raises(VoxelError, match="NaN or inf"):
        first_per_voxel(np.array([[0.0, np.nan, 0.0]]), 1.0)
    assert first_per_voxel(np.zeros((0, 3)), 1.0).shape == (0,)
