"""World-model benchmarks: the whole pipeline with a 64 x 1024 LADAR and a 256 x 256 camera at
10 Hz (real-time factor, time per stage) on the default scenario and on the village, the
densest world (houses, walls, parked cars, pedestrians: about twice the default world's
segments and tracks per sweep), What If for 100 candidate 5 s plans, What Is entity lookup and
a 64x64 map window. Medians; baselines run side by side in the same process."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

import kd_store
from bench.results import median_time, record
from kd_store import Attribute, Level, State, Status
from maps.stack import MapStack
from wm.config import NodeConfig
from wm.run import run_log
from wm.whatif import ControlPlan, Start, WhatIf
from wm.whatis import WhatIs

CMD = "make bench (python -m bench wm)"
# the whole default scenario (60 s, 450 m): a short log would weigh the node's start-up (the
# decoding process, the odometry process, the kernels' first calls: about 1 s) as a tenth of it
PIPELINE_SECONDS: float | None = None
# the village's first 30 s: its streets are dense all along, and four runs of the whole 60 s
# would double the benchmark's time for the same figure
VILLAGE_SECONDS = 30.0


def _kd_with_entities(n: int = 50) -> tuple[kd_store.KnowledgeDatabase, list[int]]:
    kd = kd_store.open()
    kd.begin_cycle(0)
    rng = np.random.default_rng(0)
    ids = []
    for i in range(n):
        attrs = {k: Attribute(estimated=1.5) for k in ("length_m", "width_m", "height_m")}
        e = kd.add_entity(f"e{i}", Level.OBJECT, generic_classes=("rock",),
                          status=Status.CONFIRMED, confidence=0.9, attributes=attrs)  # fmt: skip
        xy = rng.uniform(-40, 40, 2)
        kd.observe(e.id, State(0, "world", (*xy, 0.0), velocity_xyz=(*rng.normal(0, 1, 2), 0)))
        ids.append(e.id)
    return kd, ids


def bench_whatif() -> None:
    kd, _ = _kd_with_entities()
    stack = MapStack()
    stack.move_to(np.zeros(2))
    wi = WhatIf(kd, stack)
    plans = [ControlPlan(np.array([0.0]), np.array([v]), np.array([k]))
             for v in np.linspace(1, 10, 10) for k in np.linspace(-0.15, 0.15, 10)]  # fmt: skip
    start = Start(np.zeros(2), 0.0, 5.0, 0)
    t = median_time(lambda: wi.simulate(plans, start=start), repeat=15)
    one = median_time(lambda: wi.simulate(plans[:1], start=start), repeat=15)
    record("wm_whatif_100_plans_5s", t * 1e3, "ms", baseline="one plan per call",
           baseline_value=one * 1e3, target="at most 50 ms", command=CMD)  # fmt: skip


def bench_whatis() -> None:
    kd, ids = _kd_with_entities(1000)
    stack = MapStack()
    stack.move_to(np.zeros(2))
    wi = WhatIs(kd, stack)
    i = ids[500]
    t = median_time(lambda: [wi.entity(i) for _ in range(1000)], repeat=7) / 1000
    base = median_time(lambda: [kd.get(i) for _ in range(1000)], repeat=7) / 1000
    record("wm_whatis_entity_lookup", t * 1e6, "us", baseline="kd.get alone",
           baseline_value=base * 1e6, target="at most 20 us", command=CMD)  # fmt: skip
    lvl = stack.level("subsystem")
    tw = median_time(lambda: wi.map_window("subsystem", ("elevation",), size=64), repeat=50)
    tb = median_time(lambda: lvl.window("elevation"), repeat=50)
    record("wm_whatis_map_window_64", tw * 1e6, "us", baseline="full 256x256 level.window",
           baseline_value=tb * 1e6, target="at most 200 us", command=CMD)  # fmt: skip


def bench_pipeline() -> None:
    """The default scenario: the issue's target, 2x real time."""
    _pipeline(
        "default", PIPELINE_SECONDS, rtf_target="at least 2x real time on 2 cores",
        ms_target="at most 50 ms (2x real time at 10 Hz)",
        cpu_target="each at most 50 ms (2x real time at 10 Hz on 2 cores)",
    )  # fmt: skip


def bench_pipeline_village() -> None:
    """The village: what a live node must keep up with in a dense world, 1x real time."""
    _pipeline(
        "village", VILLAGE_SECONDS, rtf_target="at least 1x real time on 2 cores (a live node "
        "keeps up)", ms_target="at most 100 ms (1x real time at 10 Hz)",
        cpu_target="each at most 100 ms (1x real time at 10 Hz on 2 cores)",
    )  # fmt: skip


def _pipeline(
    name: str, seconds: float | None, rtf_target: str, ms_target: str, cpu_target: str
) -> None:
    """Scenario ``name`` (``seconds`` of it; None: all) simulated with the benchmark's LADAR,
    then run in a fresh process: the real-time factor and the main process's ms per sweep."""
    from fixtures.scenario import load_scenario
    from fixtures.sensors import LADAR_BENCH
    from fixtures.simulate import simulate_to_log

    # the issue's sensors: a 64 x 1024 LADAR (the scenarios' have 32 beams) and the default
    # 256 x 256 camera, both at 10 Hz
    base = load_scenario(name)
    scenario = dataclasses.replace(
        base, sensors=dataclasses.replace(base.sensors, ladar=LADAR_BENCH)
    )
    with tempfile.TemporaryDirectory() as d:
        log = simulate_to_log(scenario, Path(d) / f"{name}_64.mcap", seconds=seconds,
                              progress=False)  # fmt: skip
        # in a fresh process, as `wm run` runs: this one holds what the other benchmarks
        # left (a large heap the collector walks, warm caches of other work)
        out = subprocess.run(
            [sys.executable, "-m", "bench.bench_wm", "--pipeline", str(log)],
            capture_output=True, text=True, check=True,
            cwd=Path(__file__).resolve().parents[1],
        )  # fmt: skip
    res = json.loads(out.stdout.strip().splitlines()[-1])
    serial = _Run(**res["serial"])
    runs = [_Run(**r) for r in res["runs"]]
    rep = sorted(runs, key=lambda r: r.real_time_factor)[len(runs) // 2]  # the median run
    what = "the whole scenario" if seconds is None else f"its first {seconds:g} s"
    print(f"{name}: real-time factors:", [round(r.real_time_factor, 2) for r in runs])
    print("ms per sweep:", {k: round(v, 1) for k, v in rep.stage_ms_per_sweep.items()})
    print("CPU ms per sweep:", {k: round(v, 1) for k, v in rep.cpu_ms_per_sweep.items()})
    record(f"wm_pipeline_{name}_real_time_factor", rep.real_time_factor, "x real time",
           baseline="the same, odometry in-process", baseline_value=serial.real_time_factor,
           target=f"{rtf_target} ({what}, median of {len(runs)} runs in a fresh process; "
           "64 x 1024 LADAR)", command=CMD)  # fmt: skip
    # the main process's work per sweep (odometry runs beside it)
    record(f"wm_pipeline_{name}_main_ms_per_sweep", _main_ms(rep.stage_ms_per_sweep), "ms",
           baseline="the same, odometry in-process (registration included)",
           baseline_value=_main_ms(serial.stage_ms_per_sweep), target=ms_target,
           command=CMD)  # fmt: skip
    # CPU is less noisy than wall on a shared machine: main process and odometry process
    # must each stay under the sweep's share of the two cores
    record(f"wm_pipeline_{name}_main_cpu_ms_per_sweep", rep.cpu_ms_per_sweep["main_process"],
           "ms", baseline="the odometry process's CPU ms per sweep",
           baseline_value=rep.cpu_ms_per_sweep.get("odometry", float("nan")),
           target=cpu_target, command=CMD)  # fmt: skip


@dataclasses.dataclass
class _Run:
    real_time_factor: float
    stage_ms_per_sweep: dict[str, float]
    cpu_ms_per_sweep: dict[str, float]


def _pipeline_child(log: str, repeat: int = 3) -> None:
    """``python -m bench.bench_wm --pipeline LOG``: the serial run, then ``repeat`` runs as
    `wm run` makes them, as one JSON line."""

    def one(config: NodeConfig, decode: bool) -> dict:
        r = run_log(log, ":memory:", config=config, progress=False, decode_process=decode)
        return dataclasses.asdict(
            _Run(r.real_time_factor, r.stage_ms_per_sweep, r.cpu_ms_per_sweep)
        )

    serial = one(NodeConfig(odometry_process=False), False)
    runs = [one(NodeConfig(), True) for _ in range(repeat)]
    print(json.dumps({"serial": serial, "runs": runs}))


def _main_ms(stage_ms: dict[str, float]) -> float:
    """The node's top-level stages (the ``sp.*`` entries are parts of ``sp``)."""
    return sum(v for k, v in stage_ms.items() if "." not in k)


def main() -> None:
    bench_whatif()
    bench_whatis()
    bench_pipeline()
    bench_pipeline_village()


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--pipeline":
        _pipeline_child(sys.argv[2])
    else:
        main()
