"""The driver: frames in time order, truthful ground truth, determinism, and the MCAP log."""

from __future__ import annotations

import dataclasses
import io
from collections import Counter

import numpy as np
import pytest

from core.geometry import BODY, CAMERA, LADAR, NS_PER_S, WORLD
from fixtures.scenario import Scenario, load_scenario
from fixtures.sensors import CameraConfig, LadarConfig, OdometryConfig, SensorSuiteConfig
from fixtures.simulate import Simulator, simulate, simulate_to_log
from logs.types import (
    CameraFrame,
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    ObjectBoxes,
    OdometryFrame,
    TransformFrame,
)


def small(name: str = "default") -> Scenario:
    """A built-in scenario with small sensors, so a few frames simulate quickly."""
    sensors = SensorSuiteConfig(
        ladar=LadarConfig(n_beams=8, n_azimuth=256),
        camera=CameraConfig(width=48, height=32),
        odometry=OdometryConfig(imu=True),
    )
    return dataclasses.replace(load_scenario(name), sensors=sensors)


def test_frames_come_in_time_order_with_the_right_kinds_and_topics() -> None:
    frames = list(simulate(small(), seconds=0.35))
    t = [f.t_ns for f in frames]
    assert t == sorted(t)
    assert all(isinstance(f, TransformFrame) and f.static for f in frames[:2])
    assert {(f.child_frame_id, f.topic) for f in frames[:2]} == {
        (LADAR, "/tf_static"),
        (CAMERA, "/tf_static"),
    }
    kinds = Counter(type(f) for f in frames)
    # 0.35 s: odometry + truth at 50 Hz (t = 0 .. 0.34), sweeps that complete (0.0 .. 0.2),
    # camera at 0.05 .. 0.35
    assert kinds[OdometryFrame] == kinds[GroundTruthPose] == kinds[ImuFrame] == 18
    assert kinds[LadarScan] == kinds[ObjectBoxes] == 3
    assert kinds[CameraFrame] == 4
    topics = {type(f): f.topic for f in frames}
    assert topics[LadarScan] == "/ladar/points" and topics[CameraFrame] == "/camera"
    assert topics[OdometryFrame] == "/odom" and topics[GroundTruthPose] == "/ground_truth/pose"
    assert topics[ObjectBoxes] == "/ground_truth/objects" and topics[ImuFrame] == "/imu"


def test_ground_truth_matches_the_world() -> None:
    sim = Simulator(small())
    for f in sim.frames(0.25):
        if isinstance(f, GroundTruthPose):
            assert (f.frame_id, f.child_frame_id) == (WORLD, BODY)
            assert np.array_equal(f.T_parent_child, sim.world.T_world_body(f.t_ns))
        if isinstance(f, ObjectBoxes):
            assert np.array_equal(f.centers, sim.world.object_boxes(f.t_ns).centers)
    # the odometry starts on the truth
    first = next(f for f in sim.frames(0.1) if isinstance(f, OdometryFrame))
    assert np.allclose(first.T_parent_child, sim.world.T_world_body(0))


def _arrays(frames) -> list[np.ndarray]:
    out = []
    for f in frames:
        if isinstance(f, LadarScan):
            out += [f.points_xyz, f.intensity]
        elif isinstance(f, CameraFrame):
            out += [f.image, f.depth]
        elif isinstance(f, OdometryFrame):
            out.append(f.T_parent_child)
    return out


def test_same_seed_identical_arrays_other_seed_different() -> None:
    a = _arrays(simulate(small(), seconds=0.15, seed=4))
    b = _arrays(simulate(small(), seconds=0.15, seed=4))
    c = _arrays(simulate(small(), seconds=0.15, seed=5))
    assert len(a) == len(b) and all(
        np.array_equal(x, y, equal_nan=x.dtype.kind == "f") for x, y in zip(a, b, strict=True)
    )
    assert any(x.shape != y.shape or not np.array_equal(x, y) for x, y in zip(a, c, strict=False))


@pytest.mark.parametrize("name", ["village", "open", "parking"])
def test_other_scenarios_simulate(name: str) -> None:
    frames = list(simulate(small(name), seconds=0.1))
    scans = [f for f in frames if isinstance(f, LadarScan)]
    assert len(scans) == 1 and scans[0].n_points > 100


def test_simulate_to_log_writes_frames_terrain_and_scenario(tmp_path) -> None:
    from logs.mcap_log import McapLogSource

    scenario = small()
    path = simulate_to_log(scenario, tmp_path / "sim.mcap", seconds=0.25, seed=3, progress=False)
    assert path.exists() and not path.with_name("sim.mcap.tmp").exists()
    log = McapLogSource(path)
    attachments, metadata = log.attachments(), log.metadata()
    assert Scenario.from_yaml(attachments["scenario.yaml"].decode()) == scenario.with_seed(3)
    sim = Simulator(scenario, seed=3)
    raster = sim.world.terrain_raster()
    heights = np.load(io.BytesIO(attachments["terrain.npy"]))
    assert heights.dtype == np.float32 and np.array_equal(heights, raster.heights)
    terrain = metadata["terrain"]
    assert float(terrain["origin_x"]) == raster.origin_x
    assert float(terrain["resolution_m"]) == raster.resolution_m
    assert (int(terrain["rows"]), int(terrain["cols"])) == raster.shape
    assert terrain["frame"] == "world"
    assert metadata["scenario"] == {"name": "default", "seed": "3", "seconds": "0.25"}
    groups = {g: [int(i) for i in ids.split(",")] for g, ids in metadata["agent_groups"].items()}
    assert groups == {str(g): ids for g, ids in sim.world.groups().items()}
    assert max(len(ids) for ids in groups.values()) == 3  # the walking group
    written = Counter(type(f).__name__ for f in sim.frames(0.25))
    read = list(log.frames())
    assert Counter(type(f).__name__ for f in read) == written
    scan = next(f for f in read if isinstance(f, LadarScan))
    first = next(f for f in sim.frames(0.25) if isinstance(f, LadarScan))
    assert np.array_equal(scan.points_xyz, first.points_xyz)
    assert np.array_equal(scan.t_offset_ns, first.t_offset_ns)
    assert log.static_transforms[(BODY, LADAR)] == pytest.approx(
        scenario.sensors.ladar.T_body_ladar()
    )
    assert log.stats.backwards_timestamps == 0
    assert read[-1].t_ns <= 0.25 * NS_PER_S


def test_boxes_count_the_returns_of_their_sweep_on_each_object() -> None:
    """``n_returns`` (what the scorer calls "seen") agrees with the geometry: every counted
    return lies in its object's box, and the returns no object claims lie on the terrain."""
    from wm.evaluation import points_in_boxes
    from wm.poses import PoseTrack, deskew_to_world

    sim = Simulator(load_scenario("parking"))  # full-size sensor: rows of parked cars
    frames = list(sim.frames(0.65))
    track = PoseTrack()
    for f in frames:
        if isinstance(f, GroundTruthPose):
            track.add(f.t_ns, f.T_parent_child)
    mount = next(f.T_parent_child for f in frames if getattr(f, "child_frame_id", "") == LADAR)
    boxes = {f.t_ns: f for f in frames if isinstance(f, ObjectBoxes)}
    checked = 0
    for f in frames:
        if isinstance(f, LadarScan) and track.covers(f.t_ns + int(f.t_offset_ns.max())):
            b = boxes[f.t_ns]  # the boxes stamped at the sweep's start count its returns
            assert b.n_returns is not None
            p = deskew_to_world(f.points_xyz, f.t_offset_ns, f.t_ns, track, mount, 8)
            # boxes move little in a sweep (agents at walking and driving pace): 0.6 m margin
            grown = points_in_boxes(p, b.centers, b.sizes, b.yaws, 0.6)
            assert np.all(b.n_returns <= grown), b.ids[b.n_returns > grown]
            assert b.n_returns.max() > 200 and np.count_nonzero(b.n_returns) > 20
            terrain = np.abs(p[:, 2] - sim.world.terrain.height(p[:, 0], p[:, 1])) < 0.1
            on_objects = int(b.n_returns.sum())
            assert abs((len(p) - on_objects) - np.count_nonzero(terrain)) < 0.02 * len(p)
            checked += 1
    assert checked >= 3
