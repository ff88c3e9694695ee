"""Egosphere images (sp.egosphere) against analytic scans and a real KITTI sweep."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import kernel_scenes
import numpy as np
import pytest
from kernel_reference.egosphere_reference import to_egosphere_reference

from core.geometry import rpy_to_matrix, se3, transform_points
from logs.types import LadarScan
from sp.egosphere import (
    EgosphereConfig,
    EgosphereError,
    T_inertial_body,
    egosphere_points,
    pixel_angles,
    spherical,
    to_egosphere,
)


def scan_of(points: np.ndarray, ring: np.ndarray | None = None, t_ns: int = 0) -> LadarScan:
    n = len(points)
    return LadarScan(
        t_ns=t_ns,
        frame_id="ladar",
        points_xyz=np.asarray(points, np.float32),
        intensity=np.linspace(0, 1, n, dtype=np.float32),
        t_offset_ns=np.arange(n, dtype=np.int64) * 1000,
        ring=ring,
    )


def kitti_scan(real_data, i: int = 0) -> LadarScan:
    path = real_data / "kitti" / "sequences" / "00" / "velodyne" / f"{i:06d}.bin"
    a = np.fromfile(path, np.float32).reshape(-1, 4)
    return scan_of(a[:, :3])


def test_back_projection_returns_the_original_points(real_data):
    scan = kitti_scan(real_data)
    img = to_egosphere(scan, EgosphereConfig(max_returns=4))
    kept = np.sort(img.point_index[img.valid])
    assert kept.size + img.n_dropped + img.n_overflow == scan.n_points
    assert img.n_dropped + img.n_overflow < 0.005 * scan.n_points
    assert np.array_equal(img.back_project(), scan.points_xyz[kept])
    assert np.array_equal(img.xyz[img.valid], scan.points_xyz[img.point_index[img.valid]])


def test_pixels_hold_their_points_nearest_first(real_data):
    scan = kitti_scan(real_data)
    cfg = EgosphereConfig()
    img = to_egosphere(scan, cfg)
    both = img.valid[..., 1]
    assert both.any()
    assert np.all(img.range_m[..., 0][both] <= img.range_m[..., 1][both])
    # Every point sits in the column of its azimuth bin.
    rows, cols, ks = np.nonzero(img.valid)
    _, az, _ = spherical(img.xyz[rows, cols, ks])
    width = 2 * np.pi / cfg.n_cols
    _, az_centre = pixel_angles(cfg)
    err = np.angle(np.exp(1j * (az - az_centre[cols])))
    assert np.all(np.abs(err) <= 0.5 * width + 1e-5)
    # and the range image is the distance of that point
    r = np.linalg.norm(img.xyz[rows, cols, ks], axis=1)
    assert np.allclose(img.range_m[rows, cols, ks], r, rtol=1e-6)


def test_rings_give_rows_and_several_returns_are_kept():
    # Two returns on beam 0 (lowest) straight ahead, one on beam 3 to the left.
    pts = [[10.0, 0.0, -1.0], [4.0, 0.0, -0.4], [0.0, 5.0, 0.0]]
    cfg = EgosphereConfig(n_rows=4, n_cols=8, max_returns=2)
    img = to_egosphere(scan_of(np.array(pts), ring=np.array([0, 0, 3], np.uint16)), cfg)
    ahead_col = 4  # azimuth 0 lands just right of the middle column boundary
    assert img.point_index[3, ahead_col].tolist() == [1, 0]  # nearest first
    assert img.range_m[3, ahead_col, 0] == pytest.approx(np.hypot(4.0, 0.4))
    assert img.point_index[0, 2, 0] == 2  # azimuth +90 deg: quarter of the way from the left
    assert img.t_offset_ns[3, ahead_col].tolist() == [1000, 0]
    assert img.valid.sum() == 3


def test_frames_sensor_body_inertial_world():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-20, 20, (500, 3))
    pts[:, 2] = rng.uniform(-2, 0.5, 500)
    T_body_sensor = se3(rpy_to_matrix(0.0, 0.05, 0.0), [0.3, 0.0, 1.9])
    T_world_body = se3(rpy_to_matrix(0.02, -0.03, 1.2), [100.0, -50.0, 3.0])
    img = to_egosphere(
        scan_of(pts),
        EgosphereConfig(elevation_min_deg=-90, elevation_max_deg=90),
        T_body_sensor=T_body_sensor,
    )
    kept = np.sort(img.point_index[img.valid])
    p = pts[kept].astype(np.float32)
    world = egosphere_points(img, T_world_body, "world")
    assert np.allclose(world, transform_points(T_world_body @ T_body_sensor, p), atol=1e-4)
    inertial = egosphere_points(img, T_world_body, "inertial")
    # The inertial egosphere is the world frame moved to the body origin.
    assert np.allclose(inertial + T_world_body[:3, 3], world, atol=1e-3)
    assert np.allclose(T_inertial_body(T_world_body)[:3, 3], 0.0)


def test_empty_scan_is_an_empty_image_and_malformed_scans_are_refused():
    img = to_egosphere(scan_of(np.zeros((0, 3))))
    assert not img.valid.any() and img.back_project().shape == (0, 3)
    bad = scan_of(np.ones((5, 3)))
    bad.intensity = np.ones(4, np.float32)
    with pytest.raises(EgosphereError, match=r"intensity shape \(4,\)"):
        to_egosphere(bad)
    with pytest.raises(EgosphereError, match="elevation_max_deg"):
        EgosphereConfig(elevation_min_deg=5, elevation_max_deg=1)


# the reference casts NaN angles of dropped points to int32
@pytest.mark.filterwarnings("ignore:invalid value encountered in cast:RuntimeWarning")
def test_work_arrays_reused_across_sweeps_and_threads_leave_no_trace() -> None:
    # to_egosphere keeps its work arrays between calls (one set per thread): a large sweep,
    # a small one with more layers, then the large one again must each give their own image.
    big, small = (
        kernel_scenes.random_scan(20, 40_000, True),
        kernel_scenes.random_scan(21, 2_000, False),
    )
    cfg1 = EgosphereConfig(n_rows=64, n_cols=1024, max_returns=1)
    cfg3 = EgosphereConfig(n_rows=16, n_cols=128, max_returns=3)
    first = to_egosphere(big, cfg1)
    np.testing.assert_array_equal(first.point_index, to_egosphere_reference(big, cfg1).point_index)
    small_img = to_egosphere(small, cfg3)
    np.testing.assert_array_equal(
        small_img.point_index, to_egosphere_reference(small, cfg3).point_index
    )
    again = to_egosphere(big, cfg1)
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
