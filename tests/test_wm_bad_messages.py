"""One bad message never breaks or corrupts a run: the node logs it, counts it in
``stats.skipped`` and goes on exactly as if it had not come (the same poses, bit for bit)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from node_runs import self_poses

from sp.logs import open_log
from sp.logs.types import LadarScan, OdometryFrame


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
        np.testing.assert_array_equal(a, b)
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


def test_a_real_time_gap_starts_a_new_segment_and_the_run_goes_on(frames) -> None:
    import kd_store
    from wm.config import NodeConfig
    from wm.node import WorldModelNode

    clean, _ = self_poses(frames)
    gapped = _shifted(frames, 1.2)
    kd = kd_store.open(":memory:")
    with WorldModelNode(kd, NodeConfig()) as node:  # SP on, odometry in its own process
        cycles = [c for f in gapped for c in node.feed(f)]
        cycles += node.finish()  # the block's end finishes again: nothing more
    assert node.stats.events == {"time_jump_new_segment": 1}
    assert not node.stats.skipped  # the frames after the gap were taken, none skipped
    after = [c for c in cycles if c.t_ns > HOUR_NS]
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
        f"AND t_ns > {HOUR_NS}"
    )["n"][0].as_py()
    assert me == len(after)
    cols = kd.current_columns()
    others = cols["id"] != node.self_id
    assert int(np.sum(cols["t_ns"][others] > HOUR_NS)) >= 3
    kd.close()


def test_a_few_frames_far_in_the_future_are_skipped_not_a_new_segment(frames) -> None:
    clean, _ = self_poses(frames)
    k = next(i for i, f in enumerate(frames) if f.t_ns > frames[0].t_ns + 1_000_000_000)
    burst = [dataclasses.replace(f, t_ns=f.t_ns + HOUR_NS) for f in frames[k : k + 2]]
    spoiled, node = self_poses(frames[:k] + burst + frames[k:])
    assert not node.stats.events
    assert dict(node.stats.skipped) == {"time jump": 2}
    for a, b in zip(clean, spoiled, strict=True):
        np.testing.assert_array_equal(a, b)
