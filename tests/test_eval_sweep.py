"""The evaluation sweep (docs/evaluation.md): every scenario x the 8 evaluation seeds, 20 s
logs, 2 jobs; one JSON file per figure under results/. The targets are reported in the table
and the JSON files, not asserted; this asserts that every run completed and was scored."""

from __future__ import annotations

import math

import pytest

from bench.results import RESULTS_DIR
from wm.eval_sweep import EVAL_SEEDS, check_eval_seeds, scenarios_available, sweep


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
