"""The `wm` command line end to end: real subprocesses, real files, the messages a user sees."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

WM = [sys.executable, "-m", "wm.cli"]


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*WM, *args], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def short_log(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("cli") / "default.mcap"
    r = run("simulate", "default", "--out", str(out), "--seconds", "1", "--seed", "3")
    assert r.returncode == 0, r.stderr
    return out


def test_simulate_then_log_info_lists_every_topic(short_log):
    r = run("log-info", str(short_log))
    assert r.returncode == 0, r.stderr
    lines = {ln.split()[0]: ln.split() for ln in r.stdout.splitlines() if ln.startswith("/")}
    # 1 s at 10 Hz: sweeps and images at 10 Hz, stamped from 0 to 1 s inclusive or not.
    assert lines["/ladar/points"][1] == "sensor_msgs/msg/PointCloud2"
    assert int(lines["/ladar/points"][2]) in (10, 11)
    assert lines["/camera/image"][1] == "sensor_msgs/msg/Image"
    assert lines["/odom"][1] == "nav_msgs/msg/Odometry"
    assert lines["/ground_truth/objects"][1] == "vision_msgs/msg/Detection3DArray"
    assert "/tf_static" in lines


def test_unknown_scenario_lists_the_valid_ones(tmp_path):
    r = run("simulate", "moon", "--out", str(tmp_path / "x.mcap"), "--seconds", "1")
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    for name in ("default", "village", "open"):
        assert name in r.stderr
    assert not (tmp_path / "x.mcap").exists()


def test_truncated_log_names_the_file_without_a_traceback(short_log, tmp_path):
    cut = tmp_path / "cut.mcap"
    data = short_log.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    r = run("log-info", str(cut))
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and "cut.mcap" in r.stderr
    r = run("log-info", "--skip-corrupt", str(cut))
    assert r.returncode == 0, r.stderr
    assert "/ladar/points" in r.stdout


def test_missing_and_unsupported_paths_are_explained(tmp_path):
    r = run("log-info", str(tmp_path / "nothing.mcap"))
    assert r.returncode == 2 and "nothing.mcap" in r.stderr and "Traceback" not in r.stderr
    odd = tmp_path / "notes.txt"
    odd.write_text("hello")
    r = run("log-info", str(odd))
    assert r.returncode == 2 and "notes.txt" in r.stderr and "MCAP" in r.stderr


def test_simulate_refuses_an_output_that_is_not_mcap(tmp_path):
    r = run("simulate", "default", "--out", str(tmp_path / "x.bag"), "--seconds", "1")
    assert r.returncode == 2 and ".mcap" in r.stderr


def test_check_reports_non_finite_points(tmp_path):
    import numpy as np

    from logs import LadarScan, McapLogWriter

    pts = np.zeros((10, 3), np.float32)
    pts[:, 0] = np.arange(1, 11)
    pts[3, 1] = np.nan
    pts[7, 2] = np.inf
    path = tmp_path / "nan.mcap"
    with McapLogWriter(path) as w:
        for k in range(2):
            n = len(pts)
            scan = LadarScan(
                t_ns=k * 100_000_000,
                frame_id="ladar",
                points_xyz=pts,
                intensity=np.ones(n, np.float32),
                t_offset_ns=np.zeros(n, np.int64),
            )
            w.write(scan)
    r = run("log-info", "--check", str(path))
    assert r.returncode == 0, r.stderr
    assert "4 non-finite points dropped" in r.stdout


def test_query_reads_a_kd_file_read_only(tmp_path):
    import kd_store
    from kd_store.frames import Level, State, Status

    path = tmp_path / "run.duckdb"
    with kd_store.open(path) as kd:
        for i, (cls, x) in enumerate([("tree", 1.0), ("tree", 2.0), ("rock", 5.0)]):
            kd.add_entity(
                f"{cls}{i}",
                Level.OBJECT,
                status=Status.CONFIRMED,
                confidence=0.9,
                generic_classes=(cls,),
                state=State(t_ns=1_000, frame="world", position_xyz=(x, 0.0, 0.0)),
            )
    r = run(
        "query",
        str(path),
        "SELECT class_name, count(*) AS n, sum(x) AS sx FROM entities GROUP BY 1 ORDER BY 1",
    )
    assert r.returncode == 0, r.stderr
    rows = [ln.split() for ln in r.stdout.splitlines()]
    assert ["rock", "1", "5"] in rows and ["tree", "2", "3"] in rows
    r = run("query", str(path), "DELETE FROM entities")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    out = tmp_path / "q.parquet"
    r = run("query", str(path), "SELECT id FROM entities", "--parquet", str(out))
    assert r.returncode == 0, r.stderr
    import pyarrow.parquet as pq

    assert pq.read_table(out).num_rows == 3
