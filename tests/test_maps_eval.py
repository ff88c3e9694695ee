"""Evaluation: fused elevation on a simulated log against the simulator's true terrain.

Mapping only: points go to the world with the true poses (interpolated per point time), so
the figure measures fusion, not odometry. Recorded with ``bench.results.record``.
"""

from __future__ import annotations

import numpy as np
import pytest

from bench.results import record
from core.geometry import interpolate_pose, transform_points
from fixtures.simulate import Simulator
from logs.types import GroundTruthPose, LadarScan, ObjectBoxes, TransformFrame
from maps.fusion import range_variance
from maps.stack import MapStack

POSE_BINS = 16  # pose slices per sweep (a 0.1 s sweep at 10 m/s moves 6 cm per slice)


def _sweep_to_world(scan: LadarScan, T_body_ladar, gt_t: np.ndarray, gt_T: np.ndarray):
    """Points of one sweep in the world frame with per-point (binned) true poses."""
    off = scan.t_offset_ns
    edges = np.linspace(0, max(int(off.max()), 1), POSE_BINS + 1)
    which = np.clip(np.searchsorted(edges, off, side="right") - 1, 0, POSE_BINS - 1)
    out = np.empty(scan.points_xyz.shape, dtype=np.float64)
    for b in range(POSE_BINS):
        sel = which == b
        if not sel.any():
            continue
        t = scan.t_ns + 0.5 * (edges[b] + edges[b + 1])
        i = int(np.clip(np.searchsorted(gt_t, t) - 1, 0, len(gt_t) - 2))
        a = (t - gt_t[i]) / (gt_t[i + 1] - gt_t[i])
        T_world_ladar = interpolate_pose(gt_T[i], gt_T[i + 1], float(np.clip(a, 0, 1)))
        out[sel] = transform_points(T_world_ladar @ T_body_ladar, scan.points_xyz[sel])
    return out


def _observed(level) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Global cell keys and layer values of cells with ground points in the window."""
    count = level.window("count")
    rows, cols = np.nonzero(count > 0)
    keys = np.stack([cols + level.origin_cell[0], rows + level.origin_cell[1]], axis=1)
    vals = {n: level.window(n)[rows, cols] for n in ("elevation", "obstacle_count")}
    return keys, vals


def _cell_truth(world, keys: np.ndarray, res: float, n: int = 4) -> np.ndarray:
    """Mean true terrain height over each cell (n x n samples)."""
    f = (np.arange(n) + 0.5) / n
    du, dv = np.meshgrid(f, f, indexing="ij")
    x = (keys[:, :1] + du.ravel()[None]) * res
    y = (keys[:, 1:] + dv.ravel()[None]) * res
    return np.asarray(world.height(x, y)).mean(axis=1)


def _in_static_footprints(xy: np.ndarray, boxes: ObjectBoxes, margin_m: float) -> np.ndarray:
    """Mask: world points (N, 2) inside a static object's footprint grown by ``margin_m``
    (there the terrain is hidden under the object and the map holds its top surface)."""
    out = np.zeros(len(xy), dtype=bool)
    static = np.linalg.norm(boxes.velocities, axis=1) == 0
    parts = (boxes.centers[static], boxes.sizes[static], boxes.yaws[static])
    for c, size, yaw in zip(*parts, strict=True):
        d = xy - c[:2]
        u = d[:, 0] * np.cos(yaw) + d[:, 1] * np.sin(yaw)
        v = -d[:, 0] * np.sin(yaw) + d[:, 1] * np.cos(yaw)
        out |= (np.abs(u) <= size[0] / 2 + margin_m) & (np.abs(v) <= size[1] / 2 + margin_m)
    return out


def _agent_cells(boxes: ObjectBoxes, res: float, margin_m: float) -> set[tuple[int, int]]:
    """Global cells (res grid) under the moving objects' footprints (grown by ``margin_m``)."""
    cells: set[tuple[int, int]] = set()
    for c, size, yaw, v in zip(boxes.centers, boxes.sizes, boxes.yaws, boxes.velocities,
                               strict=True):  # fmt: skip
        if not np.any(v):
            continue
        r = 0.5 * float(np.hypot(size[0], size[1])) + margin_m
        ix = np.arange(np.floor((c[0] - r) / res), np.floor((c[0] + r) / res) + 1)
        iy = np.arange(np.floor((c[1] - r) / res), np.floor((c[1] + r) / res) + 1)
        gx, gy = np.meshgrid(ix, iy, indexing="ij")
        xy = (np.stack([gx.ravel(), gy.ravel()], axis=1) + 0.5) * res
        d = xy - c[:2]
        u = d[:, 0] * np.cos(yaw) + d[:, 1] * np.sin(yaw)
        w = -d[:, 0] * np.sin(yaw) + d[:, 1] * np.cos(yaw)
        inside = (np.abs(u) <= size[0] / 2 + margin_m) & (np.abs(w) <= size[1] / 2 + margin_m)
        cells.update(zip(gx.ravel()[inside].astype(int).tolist(),
                         gy.ravel()[inside].astype(int).tolist(), strict=True))  # fmt: skip
    return cells


@pytest.mark.eval
def test_elevation_rmse_on_simulated_default_log() -> None:
    sim = Simulator("default", seed=None)
    stack = MapStack()
    level = stack.level("subsystem")
    T_body_ladar = None
    gt_t: list[int] = []
    gt_T: list[np.ndarray] = []
    pending: list[LadarScan] = []
    boxes: ObjectBoxes | None = None
    under_agents: set[tuple[int, int]] = set()
    best: dict[tuple[int, int], tuple[float, int]] = {}
    sweeps = 0

    def checkpoint() -> None:
        keys, vals = _observed(level)
        cells = map(tuple, keys.tolist())
        for k, e, o in zip(cells, vals["elevation"], vals["obstacle_count"], strict=True):
            best[k] = (float(e), int(o))

    for frame in sim.frames():
        if isinstance(frame, TransformFrame) and frame.child_frame_id == "ladar":
            T_body_ladar = frame.T_parent_child
        elif isinstance(frame, GroundTruthPose):
            gt_t.append(frame.t_ns)
            gt_T.append(frame.T_parent_child)
        elif isinstance(frame, LadarScan):
            pending.append(frame)
        elif isinstance(frame, ObjectBoxes):
            boxes = boxes or frame
            under_agents.update(_agent_cells(frame, level.resolution_m, 0.5 * level.resolution_m))
        while pending and gt_t and gt_t[-1] >= pending[0].t_ns + int(pending[0].t_offset_ns.max()):
            scan = pending.pop(0)
            ts, Ts = np.asarray(gt_t, dtype=np.float64), np.asarray(gt_T)
            pts = _sweep_to_world(scan, T_body_ladar, ts, Ts)
            i = int(np.clip(np.searchsorted(ts, scan.t_ns), 0, len(ts) - 1))
            stack.move_to_pose(Ts[i])
            var = range_variance(np.linalg.norm(scan.points_xyz, axis=1), stack.config.fusion)
            stack.fuse(pts, variance_m2=var, t_ns=scan.t_ns)
            sweeps += 1
            if sweeps % 50 == 0:
                checkpoint()
    checkpoint()
    assert sweeps > 100
    keys = np.array(list(best), dtype=np.int64)
    est = np.array([v[0] for v in best.values()])
    obst = np.array([v[1] for v in best.values()])
    err = est - _cell_truth(sim.world, keys, level.resolution_m)
    centres = (keys + 0.5) * level.resolution_m
    hidden = _in_static_footprints(centres, boxes, 0.5 * level.resolution_m)
    hidden |= np.array([k in under_agents for k in best])
    open_ground = (obst == 0) & ~hidden
    rmse_open = float(np.sqrt(np.mean(err[open_ground] ** 2)))
    rmse_all = float(np.sqrt(np.mean(err**2)))
    record(
        "maps_elevation_rmse_0.4m_default",
        rmse_open,
        "m",
        target="< 0.05 m at the 0.4 m level, default scenario (observed cells never under an "
        "object: static footprints and the cells moving agents covered are left out)",
        command="make eval",
    )
    record(
        "maps_elevation_rmse_0.4m_default_all_cells",
        rmse_all,
        "m",
        target="reported: every cell with ground points, also under bushes, trees, roofs and "
        "cells first seen with a moving agent on them",
        command="make eval",
    )
    record(
        "maps_elevation_open_cells_0.4m_default", int(open_ground.sum()), "cells",
        target=f"reported (of {len(err)} observed cells)", command="make eval",
    )  # fmt: skip
    assert rmse_open < 0.05
