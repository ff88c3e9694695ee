"""The damaged-log and kill campaign (wm.campaign), small in `make test`, full in `make eval`:
no damaged log makes a command trace back, hang or blow up its memory; no killed run leaves a
process behind or a KD that fails `wm check`."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from wm.campaign import campaign, report

pytestmark = pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs /proc")


def _assert_clean(result) -> None:
    assert sum(result.logs.values()) > 0 or not result.every
    for bad in ("traceback", "hang", "memory", "other"):
        assert result.logs[bad] == 0, [b for b in result.bad if b.get("outcome") == bad]
    assert result.kills["orphans"] == 0, result.bad
    assert result.kills["kd_defect"] == 0 and result.kills["kd_missing"] == 0, result.bad
    assert result.kills["lost_flushed"] == 0, result.bad  # every reported flush is in the KD
    assert result.kills["max_flush_gap_ms"] <= 1100  # a kill loses at most 1 s of log


def test_a_small_campaign_finds_no_traceback_hang_or_orphan(tmp_path) -> None:
    result = campaign(6, 2, tmp_path, seed=1, timeout_s=180.0, kill_within_s=6.0)
    report(result, tmp_path / "out", "pytest tests/test_wm_campaign.py")
    assert sum(result.logs.values()) == 12 and result.kills["killed"] >= 1
    kills = [e for e in result.every if "flushed_t_ns" in e]
    assert len(kills) == 2 and kills[1]["flushed_t_ns"] is not None  # killed while producing
    _assert_clean(result)


def test_a_run_reports_each_flush_and_the_kd_holds_it(tmp_path, capsys) -> None:
    """The lines the kill campaign reads: with stderr not a terminal, ``wm run`` says at each
    flush (every second of log time) up to when the KD holds the run; the file holds it."""
    from fixtures.simulate import simulate_to_log
    from wm.campaign import flush_lines, newest_self_t_ns
    from wm.run import run_log

    log = simulate_to_log("default", tmp_path / "f.mcap", seconds=3.5, seed=5, progress=False)
    run_log(log, tmp_path / "f.kd", progress=True)
    flushed = flush_lines(capsys.readouterr().err)
    assert len(flushed) >= 3 and flushed == sorted(set(flushed))
    gaps_s = [(b - a) / 1e9 for a, b in itertools.pairwise(flushed)]
    assert all(0.9 <= g <= 1.1 for g in gaps_s), gaps_s  # every second of log, one sweep
    newest = newest_self_t_ns(tmp_path / "f.kd")
    assert newest is not None and newest >= flushed[-1]


@pytest.mark.eval
def test_the_full_campaign(tmp_path) -> None:
    from bench.results import RESULTS_DIR

    result = campaign(1000, 100, tmp_path, seed=2, timeout_s=300.0)
    report(result, RESULTS_DIR, "make eval (tests/test_wm_campaign.py::test_the_full_campaign)")
    _assert_clean(result)
