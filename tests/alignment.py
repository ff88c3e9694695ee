"""Truth in the world the KD estimates, for tests that score a run on odometry poses.

The odometry starts its own world at the first sweep (level with gravity, zero position and
yaw; ``wm.node.initial_pose``) and drifts from the truth's, so the KD's ``world`` frame differs
from the simulator's by an unknown SE(3) plus drift. As the scorer does (``wm/evaluation.py``,
``docs/evaluation.md``), truth is moved into the estimated world per time with
``T_est_true(t) = T_est(t) @ inv(T_true(t))``: a true object then sits where the KD should put
it relative to the estimated vehicle, and the comparison scores perception, not drift.

Poses are 4x4 float64 ``T_a_b`` (``p_a = T_a_b @ p_b``); times int64 ns; lengths m.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

import kd_store
from core.geometry import pose_from_xyz_quat, se3_inverse
from logs import open_log
from logs.types import GroundTruthPose, ObjectBoxes
from wm.poses import PoseTrack


def kd_self_track(kd: kd_store.KnowledgeDatabase) -> PoseTrack:
    """The KD ``self`` entity's states as a pose track ``T_est_body`` (the KD's world): what a
    user of the KD has for the vehicle, one pose a sweep."""
    self_id = kd.sql("SELECT id FROM entities WHERE name = 'self'").column("id")[0].as_py()
    s = kd.sql(
        f"SELECT t_ns, x, y, z, qx, qy, qz, qw FROM entity_states "
        f"WHERE entity_id = {int(self_id)} ORDER BY t_ns"
    ).to_pydict()
    track = PoseTrack()
    for t, *v in zip(*s.values(), strict=True):
        track.add(int(t), pose_from_xyz_quat(np.array(v[:3]), np.array(v[3:])))
    assert len(track) >= 2, "the KD's self entity has fewer than two states"
    return track


def true_pose_track(log: str | Path) -> PoseTrack:
    """The log's ``/ground_truth/pose`` as a pose track ``T_true_body`` (the truth's world)."""
    track = PoseTrack(horizon=1 << 30)
    for f in open_log(Path(log)).frames(kinds=(GroundTruthPose,)):
        track.add(f.t_ns, f.T_parent_child)
    return track


def T_est_true(est: PoseTrack, true: PoseTrack, t_ns: int) -> np.ndarray:
    """4x4: the truth's world into the estimated one at ``t_ns`` (the vehicle's true pose onto
    its estimated pose at that time)."""
    return est.at(t_ns) @ se3_inverse(true.at(t_ns))


def move_boxes(boxes: ObjectBoxes, T: np.ndarray) -> ObjectBoxes:
    """``boxes`` (M) moved by the rigid transform ``T`` (4x4): centres (M, 3), yaws (M,) about
    z (T's rotation taken as a yaw: both worlds are level with gravity), velocities (M, 3)
    rotated; ids, classes and sizes unchanged."""
    R, t = T[:3, :3], T[:3, 3]
    return dataclasses.replace(
        boxes,
        centers=boxes.centers @ R.T + t,
        yaws=boxes.yaws + float(np.arctan2(R[1, 0], R[0, 0])),
        velocities=np.nan_to_num(boxes.velocities) @ R.T,
    )


def move_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points (N, 3) or (3,) moved by the 4x4 ``T``; the same shape, float64."""
    p = np.asarray(p, dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def origin_aligned_errors(est: PoseTrack, true: PoseTrack, t_ns: list[int]) -> np.ndarray:
    """Position errors (len(t_ns),) m of the estimated poses at ``t_ns`` after aligning the
    estimated world to the true one at the first time (evo's ``align_origin``, as
    ``wm.truth.OdometryScore``): the odometry's motion since then against the truth's."""
    T_align = true.at(t_ns[0]) @ se3_inverse(est.at(t_ns[0]))  # true world <- estimated
    return np.array(
        [np.linalg.norm((T_align @ est.at(t))[:3, 3] - true.at(t)[:3, 3]) for t in t_ns]
    )
