"""Camera model (sp.camera) against OpenCV, analytic planes and the 7-Scenes depth frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from core.geometry import se3
from sp.camera import CameraError, PinholeCamera, ladar_range_in_camera

K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.05, 0.001, -0.0015, 0.0])


def test_projection_matches_opencv_with_distortion():
    cam = PinholeCamera(K, 640, 480, DIST)
    rng = np.random.default_rng(0)
    pts = np.column_stack(
        [rng.uniform(-2, 2, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(2, 9, 200)]
    )
    uv, ok = cam.project(pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, DIST)
    assert np.allclose(uv, ref.reshape(-1, 2), atol=1e-6)
    assert ok.sum() > 100


def test_back_projection_inverts_projection():
    cam = PinholeCamera(K, 640, 480, DIST)
    rng = np.random.default_rng(1)
    uv = np.column_stack([rng.uniform(20, 620, 300), rng.uniform(20, 460, 300)])
    depth = rng.uniform(0.5, 20.0, 300)
    pts = cam.back_project(uv, depth)
    assert np.allclose(pts[:, 2], depth)
    uv2, ok = cam.project(pts)
    assert ok.all() and np.abs(uv2 - uv).max() < 0.01


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"K": np.diag([-5.0, 585.0, 1.0])}, "fx=-5.0"),
        ({"K": np.array([[585.0, 0, 900.0], [0, 585.0, 240.0], [0, 0, 1]])}, "(900.0, 240.0)"),
        ({"K": np.full((3, 3), np.nan)}, "finite"),
        ({"width": 0}, "0x480"),
        ({"dist": np.array([0.1, np.inf, 0, 0, 0])}, "inf"),
    ],
)
def test_impossible_intrinsics_are_refused(kwargs, needle):
    args = {"K": K, "width": 640, "height": 480, "dist": np.zeros(5)} | kwargs
    with pytest.raises(CameraError) as err:
        PinholeCamera(**args)
    assert needle in str(err.value)


def test_wrong_image_size_is_refused():
    cam = PinholeCamera(K, 640, 480)
    with pytest.raises(CameraError, match=r"\(480, 639\)"):
        cam.check_image(np.zeros((480, 639), np.uint8))


def test_ladar_points_give_camera_pixels_their_range():
    cam = PinholeCamera(np.array([[100.0, 0, 63.5], [0, 100.0, 47.5], [0, 0, 1]]), 128, 96)
    # A wall 8 m ahead of the camera, seen by a sensor 0.5 m to the camera's left, plus a
    # nearer point in front of it that must win its pixel.
    T_camera_sensor = se3(t=[-0.5, 0.0, 0.0])
    ys, xs = np.mgrid[-4.5:4.5:0.03, -6:6:0.03]
    wall = np.column_stack([xs.ravel() + 0.5, ys.ravel(), np.full(xs.size, 8.0)])
    near = np.array([[0.5, 0.0, 2.0]])  # on the optical axis in the camera frame
    cr = ladar_range_in_camera(cam, np.vstack([wall, near]), T_camera_sensor)
    hit = np.isfinite(cr.depth_m)
    assert hit.mean() > 0.9
    centre = (48, 64)
    assert cr.point_index[centre] == len(wall) and cr.depth_m[centre] == pytest.approx(2.0)
    others = hit.copy()
    others[centre] = False
    assert np.allclose(cr.depth_m[others], 8.0, atol=1e-5)
    rows, cols = np.nonzero(others)
    ray = cam.rays(np.column_stack([cols, rows]))
    # range = depth * |ray| only approximately (the point is not at the pixel centre)
    assert np.allclose(cr.range_m[others], 8.0 * np.linalg.norm(ray, axis=1), rtol=1e-2)


def test_7scenes_depth_round_trip(real_data):
    depth_mm = cv2.imread(
        str(real_data / "7scenes" / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED
    )
    depth = np.where((depth_mm > 0) & (depth_mm < 65535), depth_mm / 1000.0, np.nan)
    cam = PinholeCamera(K, 640, 480)
    pts, rc = cam.depth_to_points(depth)
    assert len(pts) > 0.5 * depth.size
    cr = ladar_range_in_camera(cam, pts, np.eye(4))
    assert np.allclose(cr.depth_m[rc[:, 0], rc[:, 1]], depth[rc[:, 0], rc[:, 1]], atol=1e-5)
