"""The evaluation sweep (docs/evaluation.md): every scenario x the 8 evaluation seeds, 20 s
logs, 2 jobs; one JSON file per figure under results/. The targets are reported in the table
and the JSON files, not asserted; this asserts that every run completed and was scored."""

from __future__ import annotations

import math

import pytest

from bench.results import RESULTS_DIR
from wm.eval_sweep import EVAL_SEEDS, check_eval_seeds, pooled, scenarios_available, sweep, table


def test_evaluation_seeds_are_not_development_seeds():
    assert len(EVAL_SEEDS) == 8 and len(set(EVAL_SEEDS)) == 8
    assert all(s >= 1000 for s in EVAL_SEEDS)
    check_eval_seeds(scenarios_available(), EVAL_SEEDS)  # exits on a clash
    with pytest.raises(SystemExit):
        check_eval_seeds(scenarios_available(), [42])


@pytest.mark.eval
def test_sweep_over_all_scenarios_and_evaluation_seeds():
    by = sweep(["--seconds", "20", "--jobs", "2", "--out", str(RESULTS_DIR)])
    assert set(by) == set(scenarios_available())
    for scenario, runs in by.items():
        assert len(runs) == len(EVAL_SEEDS), scenario
        failed = [r for r in runs if not isinstance(r, dict)]
        assert not failed, failed
        for r in runs:
            assert r["frames"] > 100, (scenario, r)  # a 20 s log has 200 sweeps
            assert math.isfinite(r["mota"]) and math.isfinite(r["drift_pct"]), (scenario, r)


def test_a_cached_log_without_return_counts_is_simulated_again(tmp_path):
    """A log cached before the truth boxes counted returns per object would be scored by the
    older rule (returns in the grown box): the sweep simulates it again."""
    import numpy as np

    from fixtures import SIMULATOR_VERSION
    from logs import McapLogWriter
    from logs.types import ObjectBoxes
    from wm.eval_sweep import counts_returns, simulate_cached

    stale = tmp_path / f"default-seed3-0.3s-sim{SIMULATOR_VERSION}.mcap"
    with McapLogWriter(stale) as w:
        w.write(ObjectBoxes(0, "world", np.array([1]), ["rock"], np.zeros((1, 3)),
                            np.ones((1, 3)), np.zeros(1), np.zeros((1, 3))))  # fmt: skip
    assert not counts_returns(stale)
    log = simulate_cached("default", 3, 0.3, tmp_path, timeout_s=120)
    assert log == stale and counts_returns(log)


def _run(objects, misses, fps, switches, bands):
    """A seed's scores: CLEAR MOT counts and (recall, box-frames) per range band."""
    r = {"num_objects": objects, "num_misses": misses, "num_false_positives": fps,
         "num_switches": switches, "mota": 1 - (misses + fps + switches) / objects}  # fmt: skip
    for b, (rec, n) in zip(("0_20m", "20_30m", "30_40m"), bands, strict=True):
        r[f"recall_{b}"], r[f"box_frames_{b}"] = rec, n
    return r


def test_pooled_figures_weigh_each_seed_by_its_frames():
    # a seed with 2 scored box-frames and 12 false positives (MOTA -5) beside one of 100
    runs = [
        _run(2, 0, 12, 0, [(1.0, 2), (math.nan, 0), (math.nan, 0)]),
        _run(100, 10, 0, 2, [(1.0, 40), (0.8, 40), (0.5, 20)]),
    ]
    p = pooled(runs)
    assert p["mota_pooled"] == pytest.approx(1 - (12 + 10 + 2) / 102)
    assert p["recall_0_20m_pooled"] == pytest.approx(1.0)
    assert p["recall_20_30m_pooled"] == pytest.approx(0.8)
    assert p["recall_30_40m_pooled"] == pytest.approx(0.5)
    assert p["box_frames_0_20m_pooled"] == 42
    text = table("open", runs, "test")
    assert "pooled over the seeds: MOTA 0.7647" in text
    assert "20-30 m: 0.8 of 40 box-frames" in text
    # the log's start and the rest pool the same way
    for r, (start, n_start) in zip(runs, [(0.5, 2), (0.25, 20)], strict=True):
        r["recall_startup"], r["box_frames_startup"] = start, n_start
        r["recall_steady"], r["box_frames_steady"] = 1.0, r["num_objects"] - n_start
    p = pooled(runs)
    assert p["recall_startup_pooled"] == pytest.approx((1 + 5) / 22)
    assert p["recall_steady_pooled"] == pytest.approx(1.0)
    assert "first 1 s: 0.2727 of 22 box-frames; after: 1 of 80" in table("open", runs, "test")
    # no seed scored a band: NaN, not a division by zero
    assert math.isnan(pooled([_run(5, 0, 0, 0, [(1.0, 5), (math.nan, 0), (math.nan, 0)])])
                      ["recall_30_40m_pooled"])  # fmt: skip
