"""Every kind of frame is checked where it enters the node (wm.screen): a bad one among good
ones is skipped with its reason counted, the later frames are taken, and the run is the run
without it (the same self poses to summation order, so the same self states in the KD)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import pytest
from node_runs import self_poses

from logs import open_log
from logs.types import (
    CameraFrame,
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    ObjectBoxes,
    OdometryFrame,
    TransformFrame,
)
from wm.config import NodeConfig, PoseSource
from wm.screen import check_frame, finite_points

# truth poses, SP off: cheap, and every frame type still passes the node's screen
CONFIG = NodeConfig(use_sp=False, pose_source=PoseSource.TRUTH)


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> list:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("screen") / "default.mcap"
    return list(
        open_log(simulate_to_log("default", path, seconds=2.5, seed=43, progress=False)).frames()
    )


@pytest.fixture(scope="module")
def clean(frames) -> list[np.ndarray]:
    poses, node = self_poses(frames, CONFIG)
    assert not node.stats.skipped and len(poses) >= 20
    return poses


def _rot(T: np.ndarray, scale: float = 1.0, flip: bool = False) -> np.ndarray:
    T = T.copy()
    T[:3, :3] *= scale
    if flip:
        T[:3, 0] *= -1.0  # a reflection: orthonormal, det -1
    return T


def _nan(a: np.ndarray, index=(0, 0), value: float = np.nan) -> np.ndarray:
    a = np.array(a, dtype=np.float64 if a.dtype.kind != "f" else a.dtype)
    a[index] = value
    return a


def _K(c: CameraFrame, **entries: float) -> np.ndarray:
    K = c.K.copy()
    for key, v in entries.items():
        K[int(key[1]), int(key[2])] = v
    return K


def _imu(t_ns: int, **kw) -> ImuFrame:
    base = {"angular_velocity": np.zeros(3), "linear_acceleration": np.array([0, 0, 9.81])}
    return ImuFrame(t_ns, "body", **{**base, **kw})


# (kind of frame to copy, how to spoil the copy, reason counted)
Spoil = Callable[[object], object]
CASES: dict[str, tuple[type, Spoil, str]] = {
    "float time": (LadarScan, lambda s: dataclasses.replace(s, t_ns=float(s.t_ns)), "bad time"),
    "None time": (OdometryFrame, lambda o: dataclasses.replace(o, t_ns=None), "bad time"),
    "huge time": (GroundTruthPose, lambda p: dataclasses.replace(p, t_ns=2**63), "bad time"),
    "bool time": (CameraFrame, lambda c: dataclasses.replace(c, t_ns=True), "bad time"),
    "scaled transform": (
        TransformFrame,
        lambda t: dataclasses.replace(t, T_parent_child=_rot(t.T_parent_child, 1.5)),
        "bad transform",
    ),
    "NaN transform": (
        TransformFrame,
        lambda t: dataclasses.replace(t, T_parent_child=_nan(t.T_parent_child, (1, 3))),
        "bad transform",
    ),
    "reflected truth pose": (
        GroundTruthPose,
        lambda p: dataclasses.replace(p, T_parent_child=_rot(p.T_parent_child, flip=True)),
        "bad ground-truth pose",
    ),
    "inf truth pose": (
        GroundTruthPose,
        lambda p: dataclasses.replace(p, T_parent_child=_nan(p.T_parent_child, (2, 3), np.inf)),
        "bad ground-truth pose",
    ),
    "3x3 odometry pose": (
        OdometryFrame,
        lambda o: dataclasses.replace(o, T_parent_child=np.eye(3)),
        "bad odometry pose",
    ),
    "NaN odometry twist": (
        OdometryFrame,
        lambda o: dataclasses.replace(o, twist_linear=np.array([np.nan, 0.0, 0.0])),
        "bad odometry twist",
    ),
    "integer points": (
        LadarScan,
        lambda s: dataclasses.replace(s, points_xyz=s.points_xyz.astype(np.int32)),
        "bad sweep",
    ),
    "short intensity": (
        LadarScan,
        lambda s: dataclasses.replace(s, intensity=s.intensity[:-1]),
        "bad sweep",
    ),
    "float point times": (
        LadarScan,
        lambda s: dataclasses.replace(s, t_offset_ns=s.t_offset_ns.astype(np.float64)),
        "bad sweep",
    ),
    "point times of an hour": (
        LadarScan,
        lambda s: dataclasses.replace(s, t_offset_ns=s.t_offset_ns + 3600 * 10**9),
        "bad sweep",
    ),
    "no finite point": (
        LadarScan,
        lambda s: dataclasses.replace(s, points_xyz=np.full_like(s.points_xyz, np.nan)),
        "bad sweep",
    ),
    "empty sweep": (
        LadarScan,
        lambda s: dataclasses.replace(
            s,
            points_xyz=np.zeros((0, 3), np.float32),
            intensity=np.zeros(0, np.float32),
            t_offset_ns=np.zeros(0, np.int64),
            ring=None,
        ),
        "bad sweep",
    ),
    "negative focal length": (
        CameraFrame,
        lambda c: dataclasses.replace(c, K=_K(c, k00=-100.0)),
        "bad camera frame",
    ),
    "NaN intrinsics": (
        CameraFrame,
        lambda c: dataclasses.replace(c, K=_K(c, k12=np.nan)),
        "bad camera frame",
    ),
    "float image": (
        CameraFrame,
        lambda c: dataclasses.replace(c, image=c.image.astype(np.float32)),
        "bad camera frame",
    ),
    "depth of another size": (
        CameraFrame,
        lambda c: dataclasses.replace(c, depth=np.ones((3, 4), np.float32)),
        "bad camera frame",
    ),
    "negative box size": (
        ObjectBoxes,
        lambda b: dataclasses.replace(b, sizes=-np.abs(b.sizes)),
        "bad object boxes",
    ),
    "NaN box centre": (
        ObjectBoxes,
        lambda b: dataclasses.replace(b, centers=_nan(b.centers)),
        "bad object boxes",
    ),
    "infinite box velocity": (
        ObjectBoxes,
        lambda b: dataclasses.replace(b, velocities=_nan(b.velocities, value=np.inf)),
        "bad object boxes",
    ),
    "classes short of ids": (
        ObjectBoxes,
        lambda b: dataclasses.replace(b, classes=b.classes[:-1]),
        "bad object boxes",
    ),
    "NaN imu": (
        ImuFrame,
        lambda m: dataclasses.replace(m, angular_velocity=np.array([0.0, np.inf, 0.0])),
        "bad imu frame",
    ),
}


def _with_bad(frames: list, kind: type, spoil: Spoil) -> list:
    """The log with one spoiled copy of a ``kind`` frame, 1 ns after the first one past the
    log's first second (or its first one, for the transforms stamped only at the start)."""
    t1 = frames[0].t_ns + 1_000_000_000
    if kind is ImuFrame:  # the simulated log has none: a good one made up, then spoiled
        k = next(i for i, f in enumerate(frames) if f.t_ns > t1)
        src = _imu(frames[k].t_ns)
    else:
        of_kind = [i for i, f in enumerate(frames) if isinstance(f, kind)]
        k = next((i for i in of_kind if frames[i].t_ns > t1), of_kind[-1])
        src = frames[k]
    bad = spoil(dataclasses.replace(src, t_ns=src.t_ns + 1))
    return [*frames[: k + 1], bad, *frames[k + 1 :]]


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_frame_is_skipped_with_its_reason_and_changes_nothing(frames, clean, case) -> None:
    kind, spoil, reason = CASES[case]
    poses, node = self_poses(_with_bad(frames, kind, spoil), CONFIG)
    assert dict(node.stats.skipped) == {reason: 1}, case
    assert node.stats.dropped_nonfinite_points == 0
    assert len(poses) == len(clean)  # the later frames were taken: every sweep ran
    for a, b in zip(clean, poses, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-9)  # summation order


def test_a_good_imu_frame_is_taken(frames) -> None:
    assert check_frame(_imu(5, orientation_xyzw=np.array([0.0, 0.0, 0.0, 1.0]))) is None
    assert check_frame(_imu(5, orientation_xyzw=np.zeros(4))).startswith("bad imu frame")


def test_every_frame_of_a_good_log_passes_the_screen(frames) -> None:
    assert [check_frame(f) for f in frames] == [None] * len(frames)


def test_an_unknown_box_velocity_is_taken(frames) -> None:
    """NaN is the velocity of a box nobody measured it for (an annotated log's track seen
    once, as the Argoverse 2 reader gives it): the boxes are taken, infinity is not."""
    b = next(f for f in frames if isinstance(f, ObjectBoxes) and len(f) > 1)
    assert check_frame(dataclasses.replace(b, velocities=_nan(b.velocities, (1, 2)))) is None
    spoiled = dataclasses.replace(b, velocities=_nan(b.velocities, (1, 2), -np.inf))
    assert check_frame(spoiled) == "bad object boxes: velocities has non-finite values"


def test_non_finite_points_are_dropped_and_counted_not_the_sweep(frames, clean) -> None:
    """A sweep with NaN, inf and absurdly far points appended is the sweep without them: the
    points are dropped (counted in ``dropped_nonfinite_points`` and the report's skipped
    "non-finite points"), the sweep is taken and the run does not change."""
    k = [i for i, f in enumerate(frames) if isinstance(f, LadarScan)][10]
    s = frames[k]
    junk = np.array([[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf], [1e9, 0, 0]], np.float32)
    spoiled = dataclasses.replace(
        s,
        points_xyz=np.vstack([s.points_xyz, junk]),
        intensity=np.r_[s.intensity, np.zeros(4, np.float32)],
        t_offset_ns=np.r_[s.t_offset_ns, np.zeros(4, np.int64)],
        ring=None if s.ring is None else np.r_[s.ring, np.zeros(4, s.ring.dtype)],
    )
    kept, n = finite_points(spoiled)
    assert n == 4 and kept.n_points == s.n_points
    poses, node = self_poses([*frames[:k], spoiled, *frames[k + 1 :]], CONFIG)
    assert not node.stats.skipped and node.stats.dropped_nonfinite_points == 4
    for a, b in zip(clean, poses, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-9)  # summation order


def test_the_run_report_counts_dropped_points_under_skipped() -> None:
    from wm.node import NodeStats
    from wm.run import _node_skips

    stats = NodeStats()
    stats.skipped["bad sweep"] += 2
    stats.dropped_nonfinite_points = 7
    assert _node_skips(stats) == {"bad sweep": 2, "non-finite points": 7}
