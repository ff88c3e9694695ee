"""Simulator speed: one 64 x 1024 LADAR sweep of the ``default`` scenario, end to end (per-ray
poses, agents at each ray's time, noise, dropout, intensity, the LadarScan), against the bare
open3d ``RaycastingScene.cast_rays`` of the same rays on the same scene. Target: at most 3x.
Also the world build time of ``default`` (target: a few seconds at most) and the wall time
per simulated second of the demo's sensor suite."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import open3d as o3d

from bench.results import median_times_interleaved, record
from fixtures.scenario import load_scenario
from fixtures.sensors import LADAR_BENCH, SensorSuiteConfig
from fixtures.simulate import Simulator

T_NS = 12_000_000_000  # 12 s into the drive: agents and buildings in view


def main() -> None:
    scenario = dataclasses.replace(
        load_scenario("default"), sensors=SensorSuiteConfig(ladar=LADAR_BENCH)
    )
    t0 = time.perf_counter()
    sim = Simulator(scenario)
    build_s = time.perf_counter() - t0
    ladar, scene = sim.ladar, sim.world.scene
    _, origins, dirs = ladar.rays_world(T_NS)
    rays = np.empty((*dirs.shape[:2], 6), dtype=np.float32)
    rays[..., :3] = origins[:, None, :]
    rays[..., 3:] = dirs
    rays_t = o3d.core.Tensor(rays.reshape(-1, 6))

    def bare() -> None:
        scene.cast_rays(rays_t)["t_hit"].numpy()

    def sweep() -> None:
        ladar.sweep(T_NS)

    times = median_times_interleaved({"sweep": sweep, "bare": bare}, repeat=15, warmup=2)
    n_points = ladar.sweep(T_NS).n_points
    record(
        "sim_ladar_sweep_64x1024",
        times["sweep"] * 1e3,
        "ms",
        baseline="open3d RaycastingScene.cast_rays of the same 65536 rays",
        baseline_value=times["bare"] * 1e3,
        target="at most 3x the bare ray-cast",
        command="make bench (python -m bench sim)",
    )
    print(f"  {n_points} points per sweep")
    # the demo's whole sensor suite (32 x 1024 LADAR, 256 x 256 camera, 50 Hz odometry)
    demo = Simulator("default")
    t0 = time.perf_counter()
    for _ in demo.frames(seconds=3.0):
        pass
    record(
        "sim_default_wall_s_per_sim_s",
        (time.perf_counter() - t0) / 3.0,
        "s/s",
        target="faster than real time (< 1) so the 60 s demo log takes under a minute",
        command="make bench (python -m bench sim)",
    )
    record(
        "sim_world_build_default",
        build_s,
        "s",
        target="a few seconds at most",
        command="make bench (python -m bench sim)",
    )


if __name__ == "__main__":
    main()
