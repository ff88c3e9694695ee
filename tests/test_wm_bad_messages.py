"""One bad message never breaks or corrupts a run: the node logs it, counts it in
``stats.skipped`` and goes on exactly as if it had not come (the same poses, to summation order)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from node_runs import self_poses

from logs import open_log
from logs.types import LadarScan, OdometryFrame

# poses of a run with bad frames equal the clean run's to summation order: the registration's
# parallel reductions may add in another order from one run to the next (1e-17 m seen)
POSE_ATOL = 1e-9


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("bad") / "default.mcap"
    return list(
        open_log(simulate_to_log("default", path, seconds=2.5, seed=43, progress=False)).frames()
    )


def _spoiled(frames) -> list:
    """The log with seven bad messages slipped in after its first second."""
    odo = [k for k, f in enumerate(frames) if isinstance(f, OdometryFrame)]
    sweeps = [k for k, f in enumerate(frames) if isinstance(f, LadarScan)]
    k_odo = next(k for k in odo if frames[k].t_ns > frames[0].t_ns + 1_000_000_000)
    k_scan = next(k for k in sweeps if k > k_odo)
    o, s = frames[k_odo], frames[k_scan]
    nan = o.T_parent_child.copy()
    nan[0, 3] = np.nan
    scaled = o.T_parent_child.copy()
    scaled[:3, :3] *= 1.5
    zero = o.T_parent_child.copy()
    zero[:3, :3] = 0.0
    bad_odo = [
        dataclasses.replace(o, t_ns=o.t_ns + 1, T_parent_child=T) for T in (nan, scaled, zero)
    ]
    pts4 = np.hstack([s.points_xyz, np.ones((len(s.points_xyz), 1), np.float32)])
    bad_scans = [
        dataclasses.replace(s),  # the same sweep again: out of order
        dataclasses.replace(s, t_ns=s.t_ns + 1, points_xyz=pts4),  # (N, 4) points
        dataclasses.replace(s, t_ns=2 * 10**18),  # a stamp far in the future
        dataclasses.replace(s, t_ns=s.t_ns + 1, t_offset_ns=s.t_offset_ns[:5]),
    ]
    return (
        frames[: k_odo + 1]
        + bad_odo
        + frames[k_odo + 1 : k_scan + 1]
        + bad_scans
        + frames[k_scan + 1 :]
    )


def test_bad_messages_are_skipped_counted_and_change_nothing(frames) -> None:
    clean, node0 = self_poses(frames)
    spoiled, node = self_poses(_spoiled(frames))
    assert len(clean) == len(spoiled) >= 20
    for a, b in zip(clean, spoiled, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=POSE_ATOL)
    assert not node0.stats.skipped
    assert dict(node.stats.skipped) == {
        "bad odometry pose": 3,
        "sweep out of order": 1,
        "bad sweep": 2,
        "time jump": 1,
    }
    assert np.all(np.abs(spoiled[-1][:3, 3]) < 1e3)  # the self pose stayed on the ground


HOUR_NS = 3600 * 10**9


def _shifted(frames, after_s: float, by_ns: int = HOUR_NS) -> list:
    """The log with every frame after ``after_s`` seconds stamped ``by_ns`` later: a real gap
    (the recording paused), the frames after it consistent with each other."""
    cut = frames[0].t_ns + round(after_s * 1e9)
    return [dataclasses.replace(f, t_ns=f.t_ns + by_ns) if f.t_ns > cut else f for f in frames]


@pytest.mark.parametrize("gap_ns", [HOUR_NS, 30 * 10**9], ids=["hour", "30s"])
def test_a_real_time_gap_starts_a_new_segment_and_the_run_goes_on(frames, gap_ns) -> None:
    import kd_store
    from wm.config import NodeConfig
    from wm.node import WorldModelNode

    clean, _ = self_poses(frames)
    gapped = _shifted(frames, 1.2, by_ns=gap_ns)  # 30 s: within the 600 s cap, beyond the
    # bound the log's rhythm sets (a pause of seconds is integrated by nothing either)
    kd = kd_store.open(":memory:")
    with WorldModelNode(kd, NodeConfig()) as node:  # SP on, odometry in its own process
        cycles = [c for f in gapped for c in node.feed(f)]
        cycles += node.finish()  # the block's end finishes again: nothing more
    assert node.stats.events == {"time_jump_new_segment": 1}
    assert not node.stats.skipped  # the frames after the gap were taken, none skipped
    after = [c for c in cycles if c.t_ns > gap_ns]
    assert len(cycles) == len(clean) and len(after) >= 10
    assert any("new segment" in n for n in node.stats.notes)
    # the odometry restarted from the last pose: no jump of the gap times the speed; the
    # path after the gap stays within a sweep's travel of the run without a gap
    for c, T in zip(cycles, clean, strict=True):
        assert np.all(np.isfinite(c.T_world_body))
        assert np.linalg.norm(c.T_world_body[:3, 3] - T[:3, 3]) < 1.5
    # the KD goes on too: self states and entities updated after the gap
    me = kd.sql(
        f"SELECT count(*) AS n FROM entity_states WHERE entity_id = {node.self_id} "
        f"AND t_ns > {gap_ns}"
    )["n"][0].as_py()
    assert me == len(after)
    cols = kd.current_columns()
    others = cols["id"] != node.self_id
    assert int(np.sum(cols["t_ns"][others] > gap_ns)) >= 3
    kd.close()


def test_a_few_frames_far_in_the_future_are_skipped_not_a_new_segment(frames) -> None:
    clean, _ = self_poses(frames)
    k = next(i for i, f in enumerate(frames) if f.t_ns > frames[0].t_ns + 1_000_000_000)
    burst = [dataclasses.replace(f, t_ns=f.t_ns + HOUR_NS) for f in frames[k : k + 2]]
    spoiled, node = self_poses(frames[:k] + burst + frames[k:])
    assert not node.stats.events
    assert dict(node.stats.skipped) == {"time jump": 2}
    for a, b in zip(clean, spoiled, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=POSE_ATOL)


def test_one_stamp_a_minute_ahead_costs_no_minute_of_frames(frames) -> None:
    clean, _ = self_poses(frames)
    k = next(
        i for i, f in enumerate(frames)
        if isinstance(f, LadarScan) and f.t_ns > frames[0].t_ns + 1_500_000_000
    )  # fmt: skip
    ahead = dataclasses.replace(frames[k], t_ns=frames[k].t_ns + 60 * 10**9)
    spoiled, node = self_poses([*frames[:k], ahead, *frames[k:]])
    assert 2 * 10**9 <= node.jump_bound_ns() < 60 * 10**9  # the log's rhythm, not 600 s
    assert dict(node.stats.skipped) == {"time jump": 1}  # not the 10 sweeps after it
    assert not node.stats.events
    assert len(spoiled) == len(clean)
    for a, b in zip(clean, spoiled, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=POSE_ATOL)


# --- a clock that jumps back ----------------------------------------------------------------

BOUND_NS = 500_000_000  # a jump bound the 2.5 s log can cross back without negative stamps


def test_a_clock_that_jumps_back_starts_a_new_segment_and_the_run_goes_on(frames) -> None:
    """The log's clock restarts 1 s earlier at 1.2 s and runs on from there: a new segment,
    counted with a note, not every later frame skipped as out of order."""
    import kd_store
    from wm.config import NodeConfig
    from wm.node import WorldModelNode

    config = NodeConfig(max_time_jump_ns=BOUND_NS)
    clean, _ = self_poses(frames, config)
    jumped = _shifted(frames, 1.2, by_ns=-1_000_000_000)
    kd = kd_store.open(":memory:")
    with WorldModelNode(kd, config) as node:  # SP on, odometry in its own process
        cycles = [c for f in jumped for c in node.feed(f)]
        cycles += node.finish()
    assert node.stats.events == {"time_jump_new_segment": 1}
    assert not node.stats.skipped
    assert any("back" in n and "new segment" in n for n in node.stats.notes)
    assert len(cycles) == len(clean)
    back = [k for k in range(1, len(cycles)) if cycles[k].t_ns < cycles[k - 1].t_ns]
    assert len(back) == 1 and len(cycles) - back[0] >= 10  # the sweeps after it all ran
    for c, T in zip(cycles, clean, strict=True):  # the path goes on from the last pose
        assert np.all(np.isfinite(c.T_world_body))
        assert np.linalg.norm(c.T_world_body[:3, 3] - T[:3, 3]) < 1.5
    kd.close()


def test_a_few_frames_stamped_far_back_are_skipped_not_a_new_segment(frames) -> None:
    from wm.config import NodeConfig

    config = NodeConfig(use_sp=False, max_time_jump_ns=BOUND_NS)
    clean, _ = self_poses(frames, config)
    k = next(i for i, f in enumerate(frames) if f.t_ns > frames[0].t_ns + 1_500_000_000)
    burst = [dataclasses.replace(f, t_ns=f.t_ns - 1_000_000_000) for f in frames[k : k + 2]]
    spoiled, node = self_poses(frames[:k] + burst + frames[k:], config)
    assert not node.stats.events
    assert dict(node.stats.skipped) == {"time jump": 2}
    for a, b in zip(clean, spoiled, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=POSE_ATOL)


# --- the odometry survives what gets past the node's screen ---------------------------------


def _bad_wheel(o: OdometryFrame) -> list[OdometryFrame]:
    """Wheel frames the odometry must refuse: a NaN position and a rotation scaled by 1.5."""
    nan = o.T_parent_child.copy()
    nan[1, 3] = np.nan
    scaled = o.T_parent_child.copy()
    scaled[:3, :3] *= 1.5
    return [dataclasses.replace(o, t_ns=o.t_ns + 1 + i, T_parent_child=T)
            for i, T in enumerate((nan, scaled))]  # fmt: skip


def test_the_odometry_process_refuses_bad_wheel_frames_and_the_node_counts_them(frames) -> None:
    """Handed to the odometry process directly (past the node's screen), a NaN and a scaled
    wheel pose are refused there, told back with the next sweep and counted by the node; the
    run is exactly the run without them."""
    import kd_store
    from wm.config import NodeConfig
    from wm.node import WorldModelNode

    config = NodeConfig(use_sp=False)
    clean, _ = self_poses(frames, config)
    k = next(i for i, f in enumerate(frames) if isinstance(f, OdometryFrame) and i > 50)
    kd = kd_store.open(":memory:")
    with WorldModelNode(kd, config) as node:
        poses = [c.T_world_body for f in frames[: k + 1] for c in node.feed(f)]
        for bad in _bad_wheel(frames[k]):
            node.odometry.add_wheel_odometry(bad)  # the real odometry process
        poses += [c.T_world_body for f in frames[k + 1 :] for c in node.feed(f)]
        poses += [c.T_world_body for c in node.finish()]
    assert dict(node.stats.skipped) == {"bad odometry pose": 2}
    assert len(poses) == len(clean)
    for a, b in zip(clean, poses, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=POSE_ATOL)
    kd.close()


def test_a_wheel_rotation_off_by_rounding_is_taken(frames) -> None:
    """A rotation 2e-5 off orthonormal passes the node's screen: the odometry takes it too
    (re-orthonormalised), where it used to refuse it with its wheel buffer left misaligned."""
    k = next(i for i, f in enumerate(frames) if isinstance(f, OdometryFrame) and i > 50)
    T = frames[k].T_parent_child.copy()
    T[:3, :3] *= 1.0 + 1e-5
    for process in (True, False):
        from wm.config import NodeConfig

        config = NodeConfig(use_sp=False, odometry_process=process)
        clean, _ = self_poses(frames, config)
        off = [*frames[:k], dataclasses.replace(frames[k], T_parent_child=T), *frames[k + 1 :]]
        poses, node = self_poses(off, config)
        assert not node.stats.skipped and len(poses) == len(clean)
        for a, b in zip(clean, poses, strict=True):
            np.testing.assert_allclose(a, b, atol=1e-6)


def test_a_sweep_the_odometry_fails_on_is_skipped_and_it_recovers(frames) -> None:
    """A sweep that makes registration raise ((N, 4) points, past the node's screen) is
    skipped with its reason counted; the odometry restarts from its last good pose and the
    later sweeps get poses that stay on the path."""
    import kd_store
    from wm.config import NodeConfig
    from wm.node import WorldModelNode

    config = NodeConfig(use_sp=False, odometry_process=False)
    clean, _ = self_poses(frames, config)
    kd = kd_store.open(":memory:")
    cycles = []
    with WorldModelNode(kd, config) as node:
        for f in frames:
            cycles += node.feed(f)
            if len(cycles) == 8 and isinstance(f, LadarScan):
                s = f
                pts4 = np.hstack([s.points_xyz, np.ones((len(s.points_xyz), 1), np.float32)])
                bad = dataclasses.replace(s, t_ns=cycles[-1].t_ns + 1, points_xyz=pts4)
                assert node.cycle(bad) is None
        cycles += node.finish()
    assert dict(node.stats.skipped) == {"odometry failed": 1}
    assert len(cycles) == len(clean) >= 20
    for c, T in zip(cycles, clean, strict=True):
        assert np.all(np.isfinite(c.T_world_body))
        assert np.linalg.norm(c.T_world_body[:3, 3] - T[:3, 3]) < 1.0
    kd.close()


def test_the_odometry_process_replies_with_a_skip_and_goes_on(frames) -> None:
    """The odometry process itself, fed a sweep it fails on: the reply names the sweep and the
    error, the process runs on and the next sweeps get poses."""
    from wm.odometry_worker import OdometryWorker

    sweeps = [f for f in frames if isinstance(f, LadarScan)][:6]
    worker = OdometryWorker(None, None)
    try:
        replies = []
        for k, s in enumerate(sweeps):
            if k == 3:
                short = dataclasses.replace(s, t_ns=s.t_ns - 1, t_offset_ns=s.t_offset_ns[:5])
                worker.submit(short)
                replies.append(worker.result())
            worker.submit(s)
            replies.append(worker.result())
    finally:
        worker.close()
    failed = [r for r in replies if r.estimate is None]
    assert len(failed) == 1 and len(failed[0].skipped) == 1
    assert failed[0].skipped[0].startswith("odometry failed: sweep at t_ns=")
    assert "t_offset_ns" in failed[0].skipped[0]
    good = [r.estimate for r in replies if r.estimate is not None]
    assert len(good) == len(sweeps)
    assert all(np.all(np.isfinite(e.T_world_body)) for e in good)


# --- feed takes frames only -----------------------------------------------------------------


@pytest.mark.parametrize("thing", [None, {"t_ns": 0}, np.zeros((10, 3))])
def test_feed_refuses_what_is_not_a_frame_before_touching_anything(thing) -> None:
    import kd_store
    from core.errors import EngineError
    from wm.config import NodeConfig
    from wm.node import WorldModelNode

    kd = kd_store.open(":memory:")
    node = WorldModelNode(kd, NodeConfig(use_sp=False))
    with pytest.raises(TypeError, match=type(thing).__name__) as e:
        node.feed(thing)
    assert isinstance(e.value, EngineError) and "LadarScan" in str(e.value)
    assert not node.stats.frames and node.last_t_ns is None and node.odometry is None
    node.finish()
    kd.close()
