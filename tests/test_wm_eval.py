"""Evaluation: `wm run` over the whole default scenario (60 s, LADAR odometry, SP when present)
against the simulator's truth; figures recorded in results/ (``make eval``)."""

from __future__ import annotations

import pytest

from bench.results import record
from wm.config import NodeConfig
from wm.run import run_log

CMD = "make eval"


@pytest.mark.eval
def test_whole_default_scenario_against_truth(tmp_path) -> None:
    from fixtures.simulate import simulate_to_log

    log = simulate_to_log("default", tmp_path / "default.mcap", progress=False)
    # as `wm run` runs it: the log decoded ahead in a child process, a KD file with map tiles
    rep = run_log(log, tmp_path / "kd.duckdb", config=NodeConfig(), progress=False,
                  decode_process=True)  # fmt: skip
    m = rep.metrics
    odo = m["odometry"]
    record("wm_default_odometry_ate_m", odo["ate_rmse_m"], "m", target="under 1% of the path",
           command=CMD)  # fmt: skip
    record("wm_default_odometry_final_error_pct", odo["final_error_pct_of_path"], "%",
           target="under 1%", command=CMD)  # fmt: skip
    for name in ("primitive", "subsystem"):
        e = m[f"elevation_{name}"]
        record(f"wm_default_elevation_{name}_median_abs_m", e["median_abs_m"], "m",
               target="reported (includes the odometry's drift)", command=CMD)  # fmt: skip
        local = m[f"elevation_{name}_local"]  # truth moved by the last sweep's pose error
        record(f"wm_default_elevation_{name}_local_median_abs_m", local["median_abs_m"], "m",
               target="under 0.1 m", command=CMD)  # fmt: skip
    record(
        "wm_default_real_time_factor",
        rep.real_time_factor,
        "x real time",
        baseline="real time",
        baseline_value=1.0,
        target="at least 2x",
        command=CMD,
    )
    if "detection" in m:
        d = m["detection"]
        for k in ("precision", "recall", "classification_accuracy", "mota"):
            record(f"wm_default_detection_{k}", d[k], "", command=CMD)
    assert odo["final_error_pct_of_path"] < 2.0
    assert rep.sweeps >= 590
