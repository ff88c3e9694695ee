"""Every way out of a node run leaves its work in the KD file: ``finish()``, the end of a
``with WorldModelNode(...)`` block, an error inside one, and an error inside ``run_log``.

The periodic flush is pushed out of reach (``kd_flush_every_ns``), so only the first cycle's
flush and the exit path under test can have written the file; the KD is closed without a
flush of its own and read back from the file. And the run report's ``kd_flush``: how far the
file lagged behind the log between periodic flushes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from node_runs import in_file

import kd_store
from logs import LadarScan, LogError, open_log
from wm.config import NodeConfig, PoseSource
from wm.node import WorldModelNode
from wm.run import run_log

NO_PERIODIC_FLUSH = NodeConfig(kd_flush_every_ns=10**15, kd_tile_flush_every_ns=10**15)


@pytest.fixture(scope="module")
def log_path(tmp_path_factory) -> Path:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("flush") / "default.mcap"
    return simulate_to_log("default", path, seconds=3.0, seed=42, progress=False)


@pytest.fixture(scope="module")
def frames(log_path):
    return list(open_log(log_path).frames())


def test_finish_flushes_everything_to_the_file(frames, tmp_path) -> None:
    path = tmp_path / "run.kd"
    kd = kd_store.open(path)
    node = WorldModelNode(kd, NO_PERIODIC_FLUSH)
    cycles = [c for f in frames for c in node.feed(f)]
    cycles += node.finish()
    kd.close()  # no flush: only the node's own flushes reached the file
    got = in_file(path)
    assert got["self_states"] == len(cycles) >= 25
    assert got["self_t_ns"] == cycles[-1].t_pose_ns
    assert got["objects"] >= 3


def test_an_error_in_the_block_still_flushes_and_stops_the_odometry(frames, tmp_path) -> None:
    path = tmp_path / "run.kd"
    kd = kd_store.open(path)
    cycles = []
    with pytest.raises(RuntimeError, match="the controller fell over"):
        with WorldModelNode(kd, NO_PERIODIC_FLUSH) as node:
            for f in frames:
                cycles += node.feed(f)
                if f.t_ns - frames[0].t_ns > 2_000_000_000:
                    raise RuntimeError("the controller fell over")
    assert node.odometry._proc.exitcode is not None  # the odometry process has stopped
    kd.close()
    got = in_file(path)
    assert got["self_states"] == len(cycles) >= 15  # every cycle run before the error
    assert got["self_t_ns"] == cycles[-1].t_pose_ns
    assert got["objects"] >= 1


def test_a_clean_block_finishes_like_finish(frames, tmp_path) -> None:
    path = tmp_path / "run.kd"
    kd = kd_store.open(path)
    with WorldModelNode(kd, NO_PERIODIC_FLUSH) as node:
        n = sum(len(node.feed(f)) for f in frames)
    assert not node.pending and not node.inflight
    kd.close()
    assert in_file(path)["self_states"] == node.stats.sweeps > n  # the last sweeps ran too


def test_run_log_flushes_what_it_has_when_the_log_breaks(frames, tmp_path) -> None:
    # the log's sweeps as a KITTI folder (read scan by scan), the 25th of 30 damaged: the
    # run fails there, after 24 sweeps, with the KD already open
    folder = tmp_path / "velodyne"
    folder.mkdir()
    sweeps = [f for f in frames if isinstance(f, LadarScan)][:30]
    for k, s in enumerate(sweeps):
        xyzi = np.column_stack([s.points_xyz, s.intensity]).astype("<f4")
        xyzi.tofile(folder / f"{k:06d}.bin")
    with (folder / "000024.bin").open("ab") as f:
        f.write(b"\0" * 10)  # not a whole number of 16-byte points
    path = tmp_path / "run.kd"
    with pytest.raises(LogError, match=r"000024\.bin"):
        run_log(folder, path, config=NO_PERIODIC_FLUSH, progress=False)
    got = in_file(path)
    # every cycle run (24 sweeps, less the few waiting for their poses), not only the first
    assert got["self_states"] >= 18
    assert got["self_t_ns"] >= 18 * 100_000_000


# ---------------------------------------------------------------- how far the file lags


def _flush_report(log_path: Path, tmp_path: Path, config: NodeConfig) -> dict:
    """``kd_flush`` of the JSON report a 2 s run (maps only, no SP) writes to a KD file."""
    report = tmp_path / f"r{config.kd_flush_every_ns}{config.pose_source}.json"
    kd = tmp_path / f"k{config.kd_flush_every_ns}{config.pose_source}.duckdb"
    run_log(log_path, kd, config=config, report_path=report, progress=False, seconds=2.0)
    return json.loads(report.read_text())["kd_flush"]


def test_the_report_says_how_far_the_kd_file_lagged_behind_the_log(
    log_path, frames, tmp_path
) -> None:
    # a sweep's cycle runs once the log has passed its last point (one sweep period after
    # its start), and flushes once its time is an interval past the last flushed sweep's:
    # the file is behind the log by at most the interval plus one cycle
    sweeps = [f.t_ns for f in frames if isinstance(f, LadarScan)]
    period_s = float(np.max(np.diff(sweeps))) / 1e9
    truth = dict(use_sp=False, pose_source=PoseSource.TRUTH)
    every_1s = _flush_report(log_path, tmp_path, NodeConfig(**truth))
    assert every_1s["interval_s"] == 1.0
    assert 1.0 <= every_1s["max_lag_s"] <= 1.0 + period_s + 1e-6
    # 2 s of log: the first cycle, one every second after it, and the final flush
    assert every_1s["flushes"] == 4
    often = _flush_report(log_path, tmp_path, NodeConfig(**truth, kd_flush_every_ns=300_000_000))
    assert often["interval_s"] == 0.3
    assert 0.3 <= often["max_lag_s"] <= 0.3 + period_s + 1e-6
    assert often["flushes"] > every_1s["flushes"]
    # with the odometry process, `odometry_ahead` sweeps wait there too: the lag grows by them
    cfg = NodeConfig(use_sp=False, pose_source=PoseSource.ODOMETRY)
    odo = _flush_report(log_path, tmp_path, cfg)
    assert 1.0 <= odo["max_lag_s"] <= 1.0 + (1 + cfg.odometry_ahead) * period_s + 1e-6
