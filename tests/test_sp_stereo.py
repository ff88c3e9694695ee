"""Stereo disparity and range (sp.stereo) against a synthetic pair and the Middlebury cones."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sp.stereo import StereoConfig, StereoError, disparity_to_depth, stereo_disparity


def test_fronto_parallel_plane_has_its_disparity():
    rng = np.random.default_rng(0)
    left = cv2.GaussianBlur(rng.random((120, 200)).astype(np.float32), (0, 0), 1.0)
    d_true = 7
    right = np.roll(left, -d_true, axis=1)  # left (x, y) matches right (x - 7, y)
    d = stereo_disparity(left, right, StereoConfig(max_disparity_px=32))
    inner = d[10:-10, 50:-10]
    assert np.isfinite(inner).mean() > 0.9
    assert np.nanmedian(np.abs(inner - d_true)) < 0.25


def test_depth_from_disparity():
    z = disparity_to_depth(np.array([[10.0, 0.0, -1.0, np.nan]]), focal_px=500.0, baseline_m=0.2)
    assert z[0, 0] == pytest.approx(10.0)
    assert np.isnan(z[0, 1:]).all()
    with pytest.raises(StereoError, match="baseline_m=0"):
        disparity_to_depth(np.ones((2, 2)), 500.0, 0.0)


def test_bad_pairs_are_refused():
    with pytest.raises(StereoError, match=r"left \(10, 20\), right \(10, 21\)"):
        stereo_disparity(np.zeros((10, 20), np.uint8), np.zeros((10, 21), np.uint8))
    with pytest.raises(StereoError, match="exceeds the width"):
        stereo_disparity(np.zeros((10, 20), np.uint8), np.zeros((10, 20), np.uint8))
    with pytest.raises(StereoError, match="block_px"):
        StereoConfig(block_px=4)


def test_middlebury_cones(real_data):
    d = real_data / "middlebury-cones"
    left = cv2.imread(str(d / "left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(d / "right.png"), cv2.IMREAD_GRAYSCALE)
    gt = cv2.imread(str(d / "disp_left.tif"), cv2.IMREAD_UNCHANGED)
    disp = stereo_disparity(left, right)
    ok = (gt > 0) & np.isfinite(disp)
    err = np.abs(disp - gt)[ok]
    assert ok.sum() > 0.7 * (gt > 0).sum()
    assert err.mean() < 1.0 and (err > 1).mean() < 0.1
