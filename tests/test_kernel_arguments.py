"""The compiled kernels beyond their numpy references (whose equivalence is the harness,
test_kernel_equivalence.py): the arguments each refuses, naming them, and inputs a reference
cannot take or whose content a kernel must ignore."""

from __future__ import annotations

import numpy as np
import pytest
from kernel_scenes import ground_sweep

from maps.fusion import FusionError, fuse_points
from maps.level import LevelConfig, MapLevel
from maps.stack import MapStack, StackConfig, StackError
from sp.ground import GroundConfig, GroundError, ground_mask
from sp.lists import range_jump_edges
from sp.windowing import WindowingError, window_mask

# --- sp.ground ---------------------------------------------------------------------------------


def test_ground_mask_ignores_what_invalid_pixels_hold() -> None:
    """NaN, zero or junk in the empty pixels: the same mask and height (only valid pixels are
    read)."""
    results = [ground_mask(*ground_sweep(7, fill=f)) for f in ("nan", "zero", "junk")]
    for g, h in results[1:]:
        np.testing.assert_array_equal(g, results[0][0])
        assert h == results[0][1]


def test_ground_mask_rejects_mismatched_shapes() -> None:
    with pytest.raises(GroundError, match="does not match"):
        ground_mask(np.zeros((4, 5, 3)), np.zeros((4, 6), dtype=bool))
    with pytest.raises(GroundError, match="does not match"):
        ground_mask(np.zeros((4, 5, 2)), np.zeros((4, 5), dtype=bool))


def test_ground_config_refuses_a_negative_or_nan_resume_cap() -> None:
    for bad in (-0.1, float("nan")):
        with pytest.raises(GroundError, match=f"resume_max_rise_m {bad}"):
            GroundConfig(resume_max_rise_m=bad)
    assert GroundConfig(resume_max_rise_m=float("inf")).resume_max_rise_m == float("inf")


# --- sp.windowing ------------------------------------------------------------------------------


def test_window_mask_refuses_a_sigma_count_other_than_the_windows() -> None:
    c = np.random.default_rng(3).normal(0, 10, (40, 3))
    with pytest.raises(WindowingError, match="sigmas"):
        window_mask((16, 90), c, np.ones(3), np.linspace(0.3, -0.4, 16))


# --- sp.lists ----------------------------------------------------------------------------------


def test_range_edges_of_an_image_without_rows() -> None:
    """The reference's border rule indexes the last row, which an empty image lacks."""
    empty = np.zeros((0, 5), np.float32)
    assert range_jump_edges(empty, np.zeros((0, 5), bool), 0.5, 0.05).shape == (0, 5)


# --- maps.fusion -------------------------------------------------------------------------------


def test_kernel_points_refuse_bad_shapes() -> None:
    level = MapLevel(LevelConfig("t", 0.5, 16))
    with pytest.raises(FusionError, match=r"\(N, 3\).*\(4, 2\)"):
        fuse_points(level, np.zeros((4, 2)), 1e-3, t_ns=0)
    with pytest.raises(FusionError, match=r"\(4,\), got shape \(3,\)"):
        fuse_points(level, np.zeros((4, 3)), np.ones(3), t_ns=0)
    with pytest.raises(FusionError, match="variance_m2 or sensor_xyz"):
        MapStack().fuse(np.zeros((3, 3)), t_ns=0)
    with pytest.raises(FusionError, match="ray_origin_xyz"):
        fuse_points(level, np.zeros((4, 3)), 1e-3, t_ns=0, ray_origin_xyz=[0.0, np.nan, 1.0])
    with pytest.raises(StackError, match=r"raycast_levels \['subsystem'\]"):
        stack = MapStack(StackConfig(levels=(LevelConfig("a", 1.0, 8),)))
        stack.fuse(np.zeros((3, 3)), t_ns=0, variance_m2=1e-3, ray_origin_xyz=np.zeros(3))


# --- sp.computation, kd_store.covariance, sp.sweep_points, sp.voxels ---------------------------


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
