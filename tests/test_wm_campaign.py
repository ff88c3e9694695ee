"""The damaged-log and kill campaign (wm.campaign), small in `make test`, full in `make eval`:
no damaged log makes a command trace back, hang or blow up its memory; no killed run leaves a
process behind or a KD that fails `wm check`."""

from __future__ import annotations

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


def test_a_small_campaign_finds_no_traceback_hang_or_orphan(tmp_path) -> None:
    result = campaign(6, 2, tmp_path, seed=1, timeout_s=180.0, kill_within_s=6.0)
    report(result, tmp_path / "out", "pytest tests/test_wm_campaign.py")
    assert sum(result.logs.values()) == 12 and result.kills["killed"] >= 1
    _assert_clean(result)


@pytest.mark.eval
def test_the_full_campaign(tmp_path) -> None:
    from bench.results import RESULTS_DIR

    result = campaign(1000, 100, tmp_path, seed=2, timeout_s=300.0)
    report(result, RESULTS_DIR, "make eval (tests/test_wm_campaign.py::test_the_full_campaign)")
    _assert_clean(result)
