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
