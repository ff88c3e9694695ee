"""Benchmarks of the rolling maps: fusion throughput, scrolling cost, one sweep into all levels.

Baselines run side by side in the same process (``median_times_interleaved``):

* fusion of one 65 k-point sweep into one 0.4 m level, against a bare ``np.bincount``
  scatter-sum over the same cell indices (one sum, and the full set of sums fusion needs),
  and against the same fusion sums done with ``np.add.at``;
* moving a level by k rows, against filling the cleared strip of every layer, and against
  ``np.roll`` of every layer;
* fusing one sweep into all four default levels.
"""

from __future__ import annotations

import os
import statistics
import time

import numpy as np

from bench.results import median_times_interleaved, record
from maps.fusion import FusionConfig, fuse_points, range_variance
from maps.level import LevelConfig, MapLevel
from maps.stack import MapStack

N_BEAMS, N_AZIMUTH = 64, 1024  # 65 536 points
SENSOR_Z = 1.9


def synthetic_sweep(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A LADAR-like sweep around the origin: ground rings below the horizon, a wall of varying
    distance above it. Returns world points (N, 3) and ranges (N,)."""
    rng = np.random.default_rng(seed)
    az = np.repeat(np.linspace(-np.pi, np.pi, N_AZIMUTH, endpoint=False)[None], N_BEAMS, 0)
    el = np.repeat(np.radians(np.linspace(-25.0, 15.0, N_BEAMS))[:, None], N_AZIMUTH, 1)
    wall_r = 60.0 + 40.0 * np.sin(3.0 * az)
    ground_r = np.where(el < 0, SENSOR_Z / np.maximum(np.sin(-el), 1e-6), np.inf)
    horiz = np.minimum(ground_r * np.cos(el), wall_r)
    z = np.where(horiz < wall_r, 0.0, SENSOR_Z + horiz * np.tan(el))
    x, y = horiz * np.cos(az), horiz * np.sin(az)
    z = z + 0.05 * np.sin(0.2 * x) + rng.normal(0.0, 0.02, z.shape)
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    rng_m = np.linalg.norm(pts - [0.0, 0.0, SENSOR_Z], axis=1)
    return pts, rng_m


def bench_fusion(pts: np.ndarray, var: np.ndarray) -> None:
    cfg = FusionConfig()
    level = MapLevel(LevelConfig("subsystem", 0.4, 256, keep_tiles=False))
    size = level.size
    ix = np.floor(pts[:, 0] / 0.4).astype(np.int64) - level.origin_cell[0]
    iy = np.floor(pts[:, 1] / 0.4).astype(np.int64) - level.origin_cell[1]
    ok = (ix >= 0) & (ix < size) & (iy >= 0) & (iy < size)
    flat = iy[ok] * size + ix[ok]
    z, w = pts[ok, 2], 1.0 / var[ok]
    ncell = size * size
    parts = [w, w * z, np.ones_like(z), z, z * z, np.zeros_like(z)]

    def ours() -> None:
        fuse_points(level, pts, var, t_ns=0, config=cfg)

    def bare_bincount() -> None:
        np.bincount(flat, weights=z, minlength=ncell)

    def bincount_sums() -> None:
        for p in parts:
            np.bincount(flat, weights=p, minlength=ncell)
        np.minimum.at(np.full(ncell, np.inf), flat, z)
        np.maximum.at(np.full(ncell, -np.inf), flat, z)

    def add_at_sums() -> None:
        for p in parts:
            np.add.at(np.zeros(ncell), flat, p)
        np.minimum.at(np.full(ncell, np.inf), flat, z)
        np.maximum.at(np.full(ncell, -np.inf), flat, z)

    t = median_times_interleaved(
        {"ours": ours, "bare": bare_bincount, "sums": bincount_sums, "add_at": add_at_sums},
        repeat=15,
    )
    n = len(pts)
    mpts = {k: n / v / 1e6 for k, v in t.items()}
    record(
        "maps_fusion_throughput_vs_bincount",
        mpts["ours"],
        "Mpoints/s",
        baseline="one bare np.bincount scatter-sum over the same cell indices",
        baseline_value=mpts["bare"],
        target="ratio >= 0.5",
    )
    record(
        "maps_fusion_throughput_vs_bincount_sums",
        mpts["ours"],
        "Mpoints/s",
        baseline="bare np.bincount of every per-cell sum fusion needs (6 sums + min + max)",
        baseline_value=mpts["sums"],
        target="ratio >= 0.5",
    )
    unreachable = (
        f"ratio >= 5 (not reachable with numpy {np.__version__}: "
        "np.add.at is as fast as np.bincount)"
    )
    record(
        "maps_fusion_sums_bincount_vs_add_at",
        mpts["sums"],
        "Mpoints/s",
        baseline="the same per-cell sums with np.add.at",
        baseline_value=mpts["add_at"],
        target=unreachable,
    )
    record(
        "maps_fusion_throughput_vs_add_at_sums",
        mpts["ours"],
        "Mpoints/s",
        baseline="the per-cell sums alone done with np.add.at",
        baseline_value=mpts["add_at"],
        target=unreachable,
    )


def bench_move(k: int, with_tiles: bool = False) -> None:
    from maps.tiles import InMemoryTileStore

    cfg = LevelConfig("subsystem", 0.4, 256, keep_tiles=with_tiles)
    level = MapLevel(cfg, InMemoryTileStore() if with_tiles else None)
    level.write("elevation", np.zeros((1, 2)), 1.0)  # something to keep, for the tile case
    here = level.center_xy + 0.5 * level.resolution_m
    targets = [here + np.array([0.0, k * level.resolution_m]), here]  # k rows north, back
    state = {"i": 0}
    arrays = [(level.storage(n), level.specs[n].fill) for n in level.layer_names]

    def move() -> None:
        state["i"] ^= 1
        level.move_to(targets[state["i"]])

    def fill_strip() -> None:
        for arr, fill in arrays:
            arr[0:k] = fill

    def roll_all() -> None:
        for arr, _ in arrays:
            np.roll(arr, k, axis=0)

    # each pair interleaved on its own: a full-grid roll between runs would evict the cache
    t = median_times_interleaved({"move": move, "fill": fill_strip}, repeat=101)
    if k == 1 and not with_tiles:
        t_roll = median_times_interleaved({"move": move, "roll": roll_all}, repeat=51)
    tag = "_tiles" if with_tiles else ""
    record(
        f"maps_move_{k}rows{tag}_vs_fill",
        t["move"] * 1e6,
        "us",
        baseline=f"filling the cleared {k}-row strip of all {len(arrays)} layers",
        baseline_value=t["fill"] * 1e6,
        target="ratio <= 2" if not with_tiles else "reported (cells go to the tile store)",
    )
    if k == 1 and not with_tiles:
        record(
            "maps_move_1row_vs_roll",
            t_roll["move"] * 1e6,
            "us",
            baseline=f"np.roll of all {len(arrays)} layers by 1 row",
            baseline_value=t_roll["roll"] * 1e6,
            target="ratio <= 0.1",
        )


def bench_stack(pts: np.ndarray, rng_m: np.ndarray) -> None:
    stack = MapStack()
    stack.move_to(np.zeros(2))
    var = range_variance(rng_m, stack.config.fusion)
    t = median_times_interleaved(
        {"stack": lambda: stack.fuse(pts, variance_m2=var, t_ns=0)}, repeat=21
    )
    record(
        "maps_fuse_65k_sweep_all_levels",
        t["stack"] * 1e3,
        "ms",
        target="<= 10 ms median (4 levels: 0.04, 0.4, 4, 30 m)",
    )
    cpu = []
    for _ in range(21):  # the same, in this thread's CPU time: what other processes cannot inflate
        t0 = time.thread_time()
        stack.fuse(pts, variance_m2=var, t_ns=0)
        cpu.append(time.thread_time() - t0)
    record(
        "maps_fuse_65k_sweep_all_levels_cpu",
        statistics.median(cpu) * 1e3,
        "ms",
        target=f"reported (thread CPU time; load average {os.getloadavg()[0]:.1f} during the run)",
    )
    t = median_times_interleaved({"terrain": stack.update_terrain}, repeat=7)
    record("maps_update_terrain_all_levels", t["terrain"] * 1e3, "ms", target="reported")


def main() -> None:
    pts, rng_m = synthetic_sweep()
    var = range_variance(rng_m, FusionConfig())
    bench_fusion(pts, var)
    for k in (1, 8, 32):
        bench_move(k)
    bench_move(8, with_tiles=True)
    bench_stack(pts, rng_m)


if __name__ == "__main__":
    main()
