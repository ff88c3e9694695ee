"""The node's odometry never reads ground truth: its world starts at the first sweep, level with
gravity, whatever the log's ground-truth topics say; the scorer aligns estimates to the truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from node_runs import self_poses

from core.geometry import matrix_to_rpy, rpy_to_matrix, se3
from logs import open_log
from logs.types import GroundTruthPose, ObjectBoxes, OdometryFrame
from wm.node import initial_pose
from wm.poses import PoseTrack
from wm.truth import OdometryScore


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("truthfree") / "default.mcap"
    return simulate_to_log("default", path, seconds=2.5, seed=41, progress=False)


def _self_poses(frames) -> list[np.ndarray]:
    return self_poses(frames)[0]


def _falsified(f):
    """Ground truth moved 1 km away and turned: a node that reads it would move too."""
    T_lie = se3(rpy_to_matrix(0.1, -0.2, 2.0), np.array([1000.0, -500.0, 30.0]))
    if isinstance(f, GroundTruthPose):
        return dataclasses.replace(f, T_parent_child=T_lie @ f.T_parent_child)
    if isinstance(f, ObjectBoxes):
        return None
    return f


def test_odometry_is_the_same_with_lying_or_absent_ground_truth(log) -> None:
    frames = list(open_log(log).frames())
    honest = _self_poses(frames)
    lying = _self_poses([g for f in frames if (g := _falsified(f)) is not None])
    blind = _self_poses([f for f in frames if not isinstance(f, GroundTruthPose | ObjectBoxes)])
    assert len(honest) == len(lying) == len(blind) >= 20
    # equal to rounding: the registration's threads may add in another order from run to run
    # (a difference of 1e-17 m was seen); a node that read the lie would be 1 km off
    for a, b, c in zip(honest, lying, blind, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-9)
        np.testing.assert_allclose(a, c, rtol=0.0, atol=1e-9)
    # the estimated world starts near the origin, not where the truth says the vehicle is
    truth = [f for f in frames if isinstance(f, GroundTruthPose)]
    assert np.linalg.norm(truth[0].T_parent_child[:2, 3]) > 20.0
    assert np.linalg.norm(honest[0][:2, 3]) < 1.5


def test_initial_pose_takes_roll_and_pitch_only() -> None:
    T = se3(rpy_to_matrix(0.05, -0.03, 1.2), np.array([12.0, 3.0, 4.0]))
    odo = OdometryFrame(
        t_ns=0, frame_id="odom", child_frame_id="base_link", T_parent_child=T,
        twist_linear=np.zeros(3), twist_angular=np.zeros(3),
        pose_covariance=np.eye(6), twist_covariance=np.eye(6),
    )  # fmt: skip
    T0 = initial_pose(odo)
    roll, pitch, yaw = matrix_to_rpy(T0[:3, :3])
    assert (roll, pitch) == pytest.approx((0.05, -0.03), abs=1e-12)
    assert yaw == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_array_equal(T0[:3, 3], 0.0)
    bad = dataclasses.replace(odo, T_parent_child=np.diag([2.0, 2.0, 2.0, 1.0]))
    np.testing.assert_array_equal(initial_pose(bad), np.eye(4))


def test_odometry_score_aligns_at_the_first_pose() -> None:
    """Estimates in their own world (a fixed SE(3) away from the truth's) score zero error
    when they follow the true motion, and the drift when they do not."""
    truth = PoseTrack()
    T_off = se3(rpy_to_matrix(0.0, 0.0, 0.7), np.array([300.0, -40.0, 2.0]))
    score, drifting = OdometryScore(), OdometryScore()
    for k in range(11):
        truth.add(k * 100_000_000, se3(rpy_to_matrix(0, 0, 0.02 * k), np.array([k, 0.0, 0.0])))
    for k in range(11):
        T_true = truth.at(k * 100_000_000)
        score.add(k * 100_000_000, T_off @ T_true, truth)
        T_est = T_off @ T_true @ se3(t=np.array([0.01 * k, 0.0, 0.0]))
        drifting.add(k * 100_000_000, T_est, truth)
    assert score.summary()["final_error_m"] == pytest.approx(0.0, abs=1e-9)
    assert drifting.summary()["final_error_m"] == pytest.approx(0.1, abs=1e-9)
    assert drifting.summary()["final_error_pct_of_path"] == pytest.approx(1.0, rel=1e-3)


def test_a_log_without_attitude_is_levelled_on_the_first_sweeps_ground() -> None:
    """Ground tilted by the body's roll and pitch (as a LADAR on a car on a camber sees it),
    with walls and a car on it: the ground fit recovers the tilt to 0.2 degrees; a sweep with
    no ground within reach, or ground steeper than any road, gives None (the world then starts
    at the body's own attitude)."""
    from wm.node import level_from_ground

    rng = np.random.default_rng(5)
    T_world_body = se3(rpy_to_matrix(0.04, -0.03, 0.0))
    T_body_ladar = se3(t=np.array([1.2, 0.0, 1.6]))
    xy = rng.uniform(-30.0, 30.0, (20000, 2))
    ground = np.column_stack([xy, rng.normal(-0.0, 0.02, len(xy))])
    car = rng.uniform([8, -2, 0], [12.5, -0.2, 1.5], (800, 3))
    n = 1500
    wall = np.column_stack([rng.uniform(-20, 20, n), np.full(n, 9.0), rng.uniform(0, 3, n)])
    world = np.vstack([ground, car, wall])
    T_ladar_world = np.linalg.inv(T_world_body @ T_body_ladar)
    in_ladar = world @ T_ladar_world[:3, :3].T + T_ladar_world[:3, 3]
    T0 = level_from_ground(in_ladar, T_body_ladar)
    assert T0 is not None
    roll, pitch, yaw = matrix_to_rpy(T0[:3, :3])
    assert abs(roll - 0.04) < 0.0035 and abs(pitch + 0.03) < 0.0035 and abs(yaw) < 1e-9
    steep = np.column_stack([xy, 0.5 * xy[:, 0]])  # 27 degrees: no ground to level on
    assert level_from_ground(steep, np.eye(4)) is None
    assert level_from_ground(ground[np.hypot(*ground[:, :2].T) < 2.5], np.eye(4)) is None
