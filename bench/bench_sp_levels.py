"""Benchmarks of SP levels 2-5 (``python -m bench sp_levels``).

1. One 64 x 1024 simulated sweep through SP levels 1-5 and the world model's entity update
   (:class:`wm.entities.KDSensoryProcessor`: SP, then its observations written into the KD)
   together with the latest camera image (the confirmed objects' appearance,
   :mod:`sp.appearance`), median over sweeps of the default drive after a warm-up (target
   40 ms).
2. Association plus filter updates for 50 tracks: our batched filters and gated optimal
   assignment (:mod:`sp.tracking`) against a plain baseline written here, one filterpy
   ``KalmanFilter`` per track and ``linear_sum_assignment`` on Euclidean distances, on the
   same measurements, interleaved.
"""

from __future__ import annotations

import dataclasses
import statistics
import time

import numpy as np
from filterpy.kalman import KalmanFilter
from scipy.optimize import linear_sum_assignment

import kd_store
from bench.results import median_times_interleaved, record
from fixtures.scenario import load_scenario
from fixtures.sensors import LADAR_BENCH, SensorSuiteConfig
from fixtures.simulate import Simulator
from logs.types import CameraFrame, GroundTruthPose, LadarScan, TransformFrame
from sp.tracking import F_Q, Measurements, Tracker, TrackerConfig
from wm.entities import KDSensoryProcessor

N_TRACKS = 50


def bench_sweep(seconds: float = 6.0, warmup: int = 10) -> float:
    scenario = dataclasses.replace(
        load_scenario("default"), sensors=SensorSuiteConfig(ladar=LADAR_BENCH)
    )
    sim = Simulator(scenario)
    kd = kd_store.open(":memory:")
    sp = KDSensoryProcessor(kd)
    T_body_ladar = T_world_body = T_body_camera = None
    camera: CameraFrame | None = None
    times = []
    for f in sim.frames(seconds=seconds):
        if isinstance(f, TransformFrame) and f.child_frame_id == "ladar":
            T_body_ladar = f.T_parent_child
        elif isinstance(f, TransformFrame) and f.child_frame_id == "camera":
            T_body_camera = f.T_parent_child
        elif isinstance(f, GroundTruthPose):
            T_world_body = f.T_parent_child
        elif isinstance(f, CameraFrame):
            camera = f
        elif isinstance(f, LadarScan) and T_body_ladar is not None:
            T = T_world_body @ T_body_ladar
            T_cam = None if T_body_camera is None else T_world_body @ T_body_camera
            t0 = time.perf_counter()
            sp.process(f, T, camera=camera, T_world_camera=T_cam)
            times.append(time.perf_counter() - t0)
    return statistics.median(times[warmup:])


class _BaselineTracker:
    """One filterpy KalmanFilter per track and Hungarian assignment on Euclidean distance."""

    def __init__(self, xyz: np.ndarray, q_accel: float, R: np.ndarray) -> None:
        self.filters = []
        F, Q = F_Q(np.array([0.1]), q_accel)
        for p in xyz:
            kf = KalmanFilter(dim_x=6, dim_z=3)
            kf.x = np.r_[p, 0.0, 0.0, 0.0]
            kf.P = np.eye(6)
            kf.F, kf.Q, kf.R = F[0], Q[0], R
            kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
            self.filters.append(kf)

    def step(self, z: np.ndarray) -> None:
        for kf in self.filters:
            kf.predict()
        pred = np.array([kf.x[:3] for kf in self.filters])
        cost = np.linalg.norm(pred[:, None] - z[None], axis=2)
        rows, cols = linear_sum_assignment(cost)
        for r, c in zip(rows, cols, strict=True):
            if cost[r, c] < 3.0:
                self.filters[r].update(z[c])


def bench_tracks() -> dict[str, float]:
    rng = np.random.default_rng(0)
    xyz0 = rng.uniform(-50, 50, (N_TRACKS, 3))
    xyz0[:, 2] = 0.0
    vel = rng.normal(0, 3, (N_TRACKS, 3))
    vel[:, 2] = 0.0
    cfg = TrackerConfig()
    what = np.tile([2.0, 1.0, 1.5, 0.0], (N_TRACKS, 1))
    R = np.eye(3) * 0.3**2
    ours = Tracker(cfg)
    base = _BaselineTracker(xyz0, cfg.q_accel, R)
    state = {"k": 0}
    ours.step(Measurements(xyz0, np.zeros(N_TRACKS, np.int64), what), 0)

    def z_at(k: int) -> np.ndarray:
        return xyz0 + vel * 0.1 * k + rng.normal(0, 0.1, xyz0.shape)

    def run_ours() -> None:
        state["k"] += 1
        t = state["k"] * 100_000_000
        ours.step(Measurements(z_at(state["k"]), np.full(N_TRACKS, t), what), t)

    def run_base() -> None:
        base.step(z_at(state["k"]))

    return median_times_interleaved({"ours": run_ours, "base": run_base}, repeat=51, warmup=3)


def main() -> None:
    cmd = "make bench"
    sweep_s = bench_sweep()
    record(
        "sp_levels_sweep_ms",
        sweep_s * 1e3,
        "ms",
        target="<= 40 ms for one 64x1024 sweep (plus one 256x256 image)",
        command=cmd,
    )
    t = bench_tracks()
    record(
        "sp_levels_track_update_50_ms",
        t["ours"] * 1e3,
        "ms",
        baseline="filterpy KalmanFilter per track + linear_sum_assignment, same 50 tracks",
        baseline_value=t["base"] * 1e3,
        target="ratio <= 1.0",
        command=cmd,
    )


if __name__ == "__main__":
    main()
