"""Scoring against truth: the map's elevation scored with and without the odometry's drift;
detections scored without counting pairs across the range edge."""

from __future__ import annotations

import numpy as np

import kd_store
from kd_store import Level, Status
from maps.frames import rot_z, se3
from maps.level import LevelConfig, MapLevel
from sp.logs.types import ObjectBoxes
from wm.truth import DetectionScore, TerrainTruth, elevation_error


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


def test_detection_score_does_not_count_pairs_across_the_range_edge():
    """Vehicle at the origin, range 40 m, match 1 m. Scored: an object with its detection
    (hit), a detection without object (false), an object without detection (missed). Across
    the edge: a detection just inside it of an object just outside (neither false nor hit),
    and an object just inside it detected just outside (a hit, not a miss)."""
    kd = kd_store.open()
    for name, xy in {
        "hit": (10.2, 0.0),
        "inside-of-outside": (39.8, 0.0),
        "outside-of-inside": (0.0, 40.5),
        "false": (-20.0, 0.0),
    }.items():
        kd.add_entity(
            name, Level.OBJECT, generic_classes=("rock",), status=Status.CONFIRMED,
            state=kd_store.State(0, "world", (*xy, 0.0)),
        )  # fmt: skip
    centers = np.array([[10.0, 0, 0], [40.6, 0, 0], [0, 39.7, 0], [0, -20.0, 0]])
    boxes = ObjectBoxes(
        0, "world", np.arange(4), ["rock"] * 4, centers, np.ones((4, 3)), np.zeros(4),
        np.zeros((4, 3)),
    )  # fmt: skip
    score = DetectionScore(range_m=40.0, match_m=1.0)
    score.add(kd, boxes, np.zeros(2), skip=-1)
    assert (score.tp, score.fp, score.fn) == (2, 1, 1)
    assert score.class_right == 2
