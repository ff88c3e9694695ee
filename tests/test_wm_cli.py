"""`wm run`, `whatis`, `whatif`, `render` from the shell (from a log and from the KD a run
wrote): real subprocesses and files."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

WM = [sys.executable, "-m", "wm.cli"]


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*WM, *args], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def ran(tmp_path_factory) -> tuple[Path, Path, Path]:
    d = tmp_path_factory.mktemp("wmcli")
    log = d / "default.mcap"
    r = run("simulate", "default", "--out", str(log), "--seconds", "1.5", "--seed", "3")
    assert r.returncode == 0, r.stderr
    kd = d / "kd.duckdb"
    r = run("run", str(log), "--kd", str(kd), "--report", str(d / "r.json"),
            "--render", str(d / "pics"), "--no-progress")  # fmt: skip
    assert r.returncode == 0, r.stderr
    return log, kd, d


def test_run_prints_a_summary_and_writes_report_and_pictures(ran) -> None:
    _, kd, d = ran
    report = json.loads((d / "r.json").read_text())
    assert report["sweeps"] >= 10 and report["pose_source"] == "odometry"  # the default
    assert "elevation_primitive" in report["metrics"]
    assert sorted(p.name for p in (d / "pics").glob("*.png"))[0] == "level2_primitive_cost.png"
    assert kd.exists()


def test_whatis_prints_the_self_state(ran) -> None:
    _, kd, _ = ran
    r = run("whatis", str(kd))
    assert r.returncode == 0, r.stderr
    assert "vehicle, confirmed" in r.stdout and "in world" in r.stdout


def test_whatif_straight_ahead_and_bad_waypoints(ran) -> None:
    log, _, _ = ran
    r = run("whatif", str(log), "--waypoints", "0,0,0;2,10,0;4,20,0")
    assert r.returncode == 0, r.stderr
    assert "first collision:" in r.stdout and "VJ: cost" in r.stdout
    r = run("whatif", str(log), "--waypoints", "0,0,0;0,1,0")
    assert r.returncode == 2 and "times must increase" in r.stderr
    r = run("whatif", str(log), "--waypoints", "0,0,0;1,1,0", "--level", "galaxy")
    assert r.returncode == 2 and "does not exist" in r.stderr


def test_render_and_whatif_from_the_kd_alone_and_render_from_a_log(ran, tmp_path) -> None:
    log, kd, d = ran
    run_pictures = sorted(p.name for p in (d / "pics").glob("*.png"))
    r = run("render", "--kd", str(kd), str(tmp_path / "kd"))
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in (tmp_path / "kd").glob("*.png")) == run_pictures
    r = run("render", str(log), "--out", str(tmp_path / "log"), "--seconds", "0.5")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in (tmp_path / "log").glob("*.png")) == run_pictures
    r = run("whatif", "--kd", str(kd), "--waypoints", "0,0,0;2,10,0;4,20,0")
    assert r.returncode == 0, r.stderr
    assert "first collision:" in r.stdout and "VJ: cost" in r.stdout
    r = run("render", "--kd", str(kd), str(log), str(tmp_path / "both"))
    assert r.returncode == 2 and "no LOG" in r.stderr


def test_run_on_a_missing_log_is_one_clear_line(tmp_path) -> None:
    r = run("run", str(tmp_path / "none.mcap"), "--kd", str(tmp_path / "kd.duckdb"))
    assert r.returncode == 2
    assert "does not exist" in r.stderr and "Traceback" not in r.stderr
