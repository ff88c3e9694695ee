"""`wm run`, `whatis`, `whatif`, `render`, `check` from the shell (from a log and from the KD a
run wrote): real subprocesses and files."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import kd_store

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


# ---------------------------------------------------------------- wm check


def test_check_passes_the_kd_of_a_real_run_and_leaves_it_untouched(ran) -> None:
    _, kd, _ = ran
    before = kd.read_bytes()
    r = run("check", str(kd))
    assert r.returncode == 0, r.stdout + r.stderr
    assert "entity_frames: " in r.stdout and "relation_rows: " in r.stdout
    assert "defect" not in r.stdout and r.stdout.rstrip().splitlines()[-1].startswith("ok:")
    assert kd.read_bytes() == before  # opened read-only


def test_check_names_each_defect_of_a_damaged_kd(ran, tmp_path) -> None:
    import duckdb

    _, kd, _ = ran
    bad = tmp_path / "bad.duckdb"
    shutil.copyfile(kd, bad)
    con = duckdb.connect(str(bad))
    self_id = con.execute("SELECT id FROM entity_frames WHERE name = 'self'").fetchall()[0][0]
    # another entity with states: one of them gets a NaN position
    other = con.execute(
        f"SELECT min(entity_id) FROM entity_state_rows WHERE entity_id <> {self_id}"
    ).fetchall()[0][0]
    con.execute(f"DELETE FROM entity_frames WHERE id = {self_id}")  # its states are orphans
    con.execute(
        "UPDATE entity_state_rows SET x = 'nan'::DOUBLE WHERE rowid = "
        f"(SELECT min(rowid) FROM entity_state_rows WHERE entity_id = {other})"
    )
    con.close()
    r = run("check", str(bad))
    assert r.returncode == 2, r.stdout + r.stderr
    defects = [line for line in r.stdout.splitlines() if line.startswith("defect:")]
    assert len(defects) == 2, r.stdout
    assert "orphan_state in entity_state_rows: 1 " in defects[0]
    assert f"(ids {self_id})" in defects[0]
    assert "nonfinite_position in entity_state_rows: 1 " in defects[1]
    assert f"(ids {other})" in defects[1]
    assert "2 kinds of defect" in r.stderr


def test_check_names_events_and_relations_left_pointing_at_a_deleted_entity(ran, tmp_path):
    import duckdb

    _, kd, _ = ran
    bad = tmp_path / "bad.duckdb"
    shutil.copyfile(kd, bad)
    con = duckdb.connect(str(bad))
    event, entity = con.execute(
        "SELECT min(src_id), min_by(dst_id, src_id) FROM relation_rows WHERE kind = 'involves' "
        "AND src_id IN (SELECT id FROM event_frames)"
    ).fetchall()[0]
    con.execute(f"DELETE FROM entity_frames WHERE id = {entity}")
    con.close()
    r = run("check", str(bad))
    assert r.returncode == 2, r.stdout + r.stderr
    kinds = {line.split()[1]: line for line in r.stdout.splitlines() if line.startswith("defect:")}
    assert f"(ids {event})" in kinds["event_missing_entity"]
    assert str(entity) in kinds["dangling_relation"].split("(ids ")[1]


def test_check_of_a_file_that_is_not_a_kd_is_one_clear_line(tmp_path) -> None:
    import duckdb

    text = tmp_path / "notes.duckdb"
    text.write_text("not a database\n")
    other = tmp_path / "other.duckdb"
    duckdb.connect(str(other)).execute("CREATE TABLE t (a INTEGER)").close()
    for path, why in ((text, "cannot open"), (other, "not a KD file")):
        r = run("check", str(path))
        assert r.returncode == 2 and r.stdout == "", r.stdout + r.stderr
        assert r.stderr.count("\n") == 1 and why in r.stderr and str(path) in r.stderr


# ---------------------------------------------------------------- wm run into a KD that exists


def test_run_refuses_an_existing_kd_unless_overwrite_or_append(ran, tmp_path) -> None:
    log, kd, _ = ran
    old = tmp_path / "old.duckdb"
    shutil.copyfile(kd, old)
    before = old.read_bytes()
    r = run("run", str(log), "--kd", str(old), "--no-progress")
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "the file exists; give --append to add this run to it or --overwrite" in r.stderr
    assert r.stdout == ""
    assert old.read_bytes() == before
    # not even --overwrite replaces a file that is no KD (the log, by a slip of the shell)
    r = run("run", str(log), "--kd", str(log), "--overwrite", "--no-progress")
    assert r.returncode == 2 and "not a DuckDB file" in r.stderr and log.stat().st_size > 0
    # --overwrite: a new run, shorter than the first, replaces the file (not added to it)
    r = run("run", str(log), "--kd", str(old), "--overwrite", "--seconds", "0.3",
            "--no-progress", "--decode-in-process")  # fmt: skip
    assert r.returncode == 0, r.stderr
    selves = "SELECT count(*) FROM entities WHERE name = 'self'"
    states = "SELECT count(*) FROM entity_states s JOIN entities e ON e.id = s.entity_id"
    with kd_store.open(kd, read_only=True) as first, kd_store.open(old, read_only=True) as new:
        assert new.sql(selves).columns[0][0].as_py() == 1
        n_first = first.sql(f"{states} WHERE e.name = 'self'").columns[0][0].as_py()
        n_new = new.sql(f"{states} WHERE e.name = 'self'").columns[0][0].as_py()
    assert 1 <= n_new < n_first
    # --append: the same short run added to a copy of the first KD as run 1; run 0 untouched
    both = tmp_path / "both.duckdb"
    shutil.copyfile(kd, both)
    r = run("run", str(log), "--kd", str(both), "--append", "--overwrite", "--no-progress")
    assert r.returncode == 2 and "give one" in r.stderr, r.stderr
    r = run("run", str(log), "--kd", str(both), "--append", "--seconds", "0.3",
            "--no-progress", "--decode-in-process")  # fmt: skip
    assert r.returncode == 0, r.stderr
    per_run = (
        "SELECT count(*) FROM entity_states s JOIN entities e ON e.id = s.entity_id "
        "WHERE e.name = 'self' AND s.run_id = {run} AND e.run_id = {run}"
    )
    with kd_store.open(both, read_only=True) as b, kd_store.open(kd, read_only=True) as first:
        assert b.run_id == 1
        runs = b.sql("SELECT run_id, source FROM runs ORDER BY run_id").to_pylist()
        assert runs == [{"run_id": 0, "source": str(log)}, {"run_id": 1, "source": str(log)}]
        assert b.sql(per_run.format(run=0)).columns[0][0].as_py() == n_first
        assert b.sql(per_run.format(run=1)).columns[0][0].as_py() == n_new
        for view in ("entities", "events", "map_tiles"):
            q = f"SELECT count(*) FROM {view}"
            n0 = b.sql(f"{q} WHERE run_id = 0").columns[0][0].as_py()
            assert n0 == first.sql(q).columns[0][0].as_py() > 0, view
    assert run("check", str(both)).returncode == 0
    r = run("whatis", str(both), "--run", "0")  # run 0's self, as in the first KD alone
    assert r.returncode == 0 and r.stdout == run("whatis", str(kd)).stdout, r.stderr
    assert run("whatis", str(both)).stdout != r.stdout  # the newest run: another self


# ---------------------------------------------------------------- a run that produced nothing


def test_run_of_a_log_without_sweeps_says_what_it_lacked_and_exits_2(tmp_path) -> None:
    from core.geometry import se3
    from logs import McapLogWriter, OdometryFrame

    log = tmp_path / "odometry_only.mcap"
    with McapLogWriter(log) as w:  # 0.4 s of wheel odometry at 50 Hz, no LADAR
        for k in range(20):
            w.write(OdometryFrame(
                t_ns=1_000_000_000 + k * 20_000_000, frame_id="odom", child_frame_id="base_link",
                T_parent_child=se3(np.eye(3), np.array([0.1 * k, 0.0, 0.0])),
                twist_linear=np.array([5.0, 0.0, 0.0]), twist_angular=np.zeros(3),
            ))  # fmt: skip
    report = tmp_path / "r.json"
    r = run("run", str(log), "--kd", str(tmp_path / "k.duckdb"), "--report", str(report),
            "--no-progress", "--decode-in-process")  # fmt: skip
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert "no PointCloud2 sweep on any topic; topics are: /odom (nav_msgs/msg/Odometry)" in (
        r.stderr
    )
    assert json.loads(report.read_text())["sweeps"] == 0  # the report is still written
