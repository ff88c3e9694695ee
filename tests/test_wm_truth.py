"""Scoring against truth: the map's elevation scored with and without the odometry's drift
(tracking is scored by wm.evaluation: tests/test_evaluation.py)."""

from __future__ import annotations

import numpy as np

from core.geometry import rot_z, se3
from maps.level import LevelConfig, MapLevel
from wm.truth import TerrainTruth, elevation_error


def _tilted_truth() -> TerrainTruth:
    ys, xs = np.mgrid[0:41, 0:41].astype(np.float64)
    return TerrainTruth(0.05 * (xs - 20) + 0.02 * (ys - 20), (-20.0, -20.0), 1.0)


def test_elevation_error_without_drift_is_zero_and_drift_is_removed_by_the_pose_error():
    truth = _tilted_truth()
    level = MapLevel(LevelConfig("t", 0.5, 32, keep_tiles=False))
    rows, cols = np.nonzero(np.ones((32, 32)))
    xy = level.window_to_world(rows, cols)
    # A map built under drifted poses: everything moved by T_est_true (2 m up, 0.05 rad yaw).
    T_est_true = se3(rot_z(0.05), [0.3, -0.2, 2.0])
    p_true = np.column_stack([xy, truth.height(xy)])
    p_est = p_true @ T_est_true[:3, :3].T + T_est_true[:3, 3]
    level.write("elevation", p_est[:, :2], p_est[:, 2])
    level.write("count", p_est[:, :2], np.ones(len(p_est)))
    level.write("obstacle_count", p_est[:, :2], np.zeros(len(p_est)))

    raw = elevation_error(level, truth)
    assert raw["median_abs_m"] > 1.5  # the drift is all there is to see
    T_true_est = np.linalg.inv(T_est_true)
    local = elevation_error(level, truth, T_true_est)
    # left: only the cell quantisation of the moved points on a 5 % slope
    assert local["median_abs_m"] < 0.03 and local["cells"] > 500
