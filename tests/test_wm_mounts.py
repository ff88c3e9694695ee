"""The LADAR's mount: SP looks from the sensor whatever frame a log gives its sweeps in.

A simulated log is rewritten two ways a user's recordings come: sweeps in ``base_link``
(points moved by the mount, as Argoverse 2 and some ROS pipelines publish them), and sweeps in
a frame named by the driver (``velodyne``) with the mount published under that name. The node
must see the same egosphere as from the original log, and the evaluation must count the same
returns on the true boxes."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import kd_store
from core.geometry import BODY, LADAR
from fixtures.simulate import Simulator
from logs.mcap_log import McapLogWriter
from logs.types import LadarScan, ObjectBoxes, TransformFrame
from wm.config import NodeConfig, PoseSource
from wm.evaluation import load_truth
from wm.node import WorldModelNode

SECONDS = 1.5


@pytest.fixture(scope="module")
def frames() -> list:
    return list(Simulator("default", seed=5).frames(SECONDS))


def _mount(frames: list) -> np.ndarray:
    tf = [f for f in frames if isinstance(f, TransformFrame) and f.child_frame_id == LADAR]
    return tf[0].T_parent_child


def _rewritten(frames: list, how: str) -> list:
    T = _mount(frames)
    out = []
    for f in frames:
        if isinstance(f, LadarScan) and how == "base_link":
            p = f.points_xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
            f = dataclasses.replace(f, points_xyz=p.astype(np.float32), frame_id=BODY)
        elif isinstance(f, LadarScan):
            f = dataclasses.replace(f, frame_id="velodyne")
        elif isinstance(f, TransformFrame) and f.child_frame_id == LADAR and how == "velodyne":
            f = dataclasses.replace(f, child_frame_id="velodyne")
        out.append(f)
    return out


def _run(frames: list) -> tuple[WorldModelNode, list]:
    node = WorldModelNode(kd_store.open(":memory:"), NodeConfig(pose_source=PoseSource.TRUTH))
    cycles = []
    for f in frames:
        cycles += node.feed(f)
    return node, cycles + node.finish()


@pytest.fixture(scope="module")
def original(frames: list) -> tuple[WorldModelNode, list]:
    return _run(frames)


@pytest.mark.parametrize("how", ["base_link", "velodyne"])
def test_the_node_looks_from_the_sensor_whatever_the_sweeps_frame(
    frames: list, original: tuple, how: str
) -> None:
    _, cycles0 = original
    node, cycles = _run(_rewritten(frames, how))
    np.testing.assert_allclose(node.T_body_ladar, _mount(frames))
    assert not any("LADAR taken at the body" in n for n in node.stats.notes)
    assert len(cycles) == len(cycles0) >= 10
    for c0, c in zip(cycles0, cycles, strict=True):
        g0, g = c0.sp_result.ground_mask, c.sp_result.ground_mask
        assert g0.sum() > 1000
        # float32 rounding of the moved points may move a return across a pixel border
        assert (g0 != g).mean() < 1e-3
        n0, n = len(c0.sp_result.points_world), len(c.sp_result.points_world)
        assert abs(n - n0) <= 1e-3 * n0
        np.testing.assert_allclose(
            c.sp_result.points_world.mean(axis=0), c0.sp_result.points_world.mean(axis=0), atol=0.01
        )


def test_without_a_mount_the_body_is_taken_and_said(frames: list) -> None:
    bare = [f for f in _rewritten(frames, "velodyne") if not isinstance(f, TransformFrame)]
    node, cycles = _run(bare)
    assert cycles and np.array_equal(node.T_body_ladar, np.eye(4))
    assert any("no base_link->velodyne transform" in n for n in node.stats.notes)


def test_the_evaluation_counts_body_frame_sweeps_in_the_body(frames: list, tmp_path: Path) -> None:
    """Without the simulator's per-box return counts, the evaluation counts the returns in
    each box after moving them to the world through the mount of the sweeps' frame."""
    seen = {}
    for how, fs in (("ladar", frames), ("base_link", _rewritten(frames, "base_link"))):
        path = tmp_path / f"{how}.mcap"
        with McapLogWriter(path) as w:
            for f in fs:
                if isinstance(f, ObjectBoxes):  # as a real log: no per-box return counts
                    f = dataclasses.replace(f, n_returns=None)
                w.write(f)
        truth = load_truth(path)
        seen[how] = np.concatenate([s.points for s in truth.seen if s.ids is not None])
        expected = _mount(frames) if how == "ladar" else np.eye(4)
        np.testing.assert_allclose(truth.T_body_ladar, expected)
    assert seen["ladar"].sum() > 100
    assert np.abs(seen["ladar"] - seen["base_link"]).sum() <= 0.01 * seen["ladar"].sum()
