"""`wm run` over a simulated log damaged byte-wise: a duplicated chunk stops it with one
clear line, or with --skip-corrupt is skipped and counted as the messages lost; damaged
terrain truth (only used for scoring) disables that score with a note, never the run; and
`wm evaluate`'s truth loading says plainly when the truth is unavailable."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from test_logs_corrupt import _chunks, _copy, _duplicate_chunk

from wm.config import NodeConfig
from wm.evaluation import EvaluationError, load_truth
from wm.run import run_log


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory) -> Path:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("damaged") / "default.mcap"
    return simulate_to_log("default", path, seconds=1.5, seed=3, progress=False)


def test_duplicated_chunk_stops_the_run_or_is_skipped_and_counted(sim_log, tmp_path) -> None:
    data = bytearray(sim_log.read_bytes())
    big = max(range(len(_chunks(bytes(data)))), key=lambda k: _chunks(bytes(data))[k][2])
    edited, copy_at, n = _duplicate_chunk(data, big, at_end=True)
    bad = tmp_path / "dup.mcap"
    bad.write_bytes(bytes(edited))
    cmd = [sys.executable, "-m", "wm.cli", "run", str(bad), "--kd", str(tmp_path / "a.duckdb")]
    r = subprocess.run([*cmd, "--no-progress"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and f"CHUNK at byte {copy_at} repeats" in r.stderr
    assert "Traceback" not in r.stderr
    r = subprocess.run(
        [*cmd[:-1], str(tmp_path / "b.duckdb"), "--no-progress", "--skip-corrupt",
         "--report", str(tmp_path / "r.json")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["skipped"].get("duplicated chunk") == n > 0
    # the copies never reached the node: nothing out of order there
    assert not any("out of order" in k for k in report["skipped"])
    assert any(f"CHUNK at byte {copy_at} repeats" in note for note in report["notes"])
    with pytest.raises(EvaluationError, match=r"ground truth unavailable: .*repeats the chunk"):
        load_truth(bad)


@pytest.mark.parametrize("what", ["attachment", "metadata"])
def test_damaged_terrain_truth_disables_its_score_not_the_run(sim_log, tmp_path, what) -> None:
    def spoil(d: bytearray) -> bytearray:
        if what == "attachment":  # one bit of the heights: the attachment's CRC fails
            at = bytes(d).index(b"\x93NUMPY") + 5000
            d[at] ^= 0x10
        else:  # the grid's origin is no number
            at = bytes(d).index(b"origin_x") + len("origin_x") + 4
            d[at] = ord("x")
        return d

    bad = _copy(sim_log, tmp_path / f"{what}.mcap", spoil)
    config = NodeConfig(use_sp=False)
    report = run_log(bad, config=config, progress=False, seconds=0.6)
    assert report.sweeps > 0
    assert not any(k.startswith("elevation_") for k in report.metrics)
    why = report.metrics["elevation"]["disabled"]
    assert ("CRC mismatch" if what == "attachment" else "ValueError") in why
    assert any(n.startswith("elevation scores disabled: ") for n in report.notes)
    good = run_log(sim_log, config=config, progress=False, seconds=0.6)
    assert "elevation_primitive" in good.metrics and "elevation" not in good.metrics
