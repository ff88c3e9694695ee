"""Occupancy with free-space ray casting on a simulated log, against the simulator's objects.

Points go to the world with the true poses (per point time, binned), the ray origin is the
true LADAR position at mid-sweep, so the figures measure the occupancy update, not odometry.
Occupied cells (log-odds > 0) of the 0.4 m level should fall on true objects; free cells
(log-odds < 0) should not fall inside solid objects (trees are left out of that check: beams
pass under their crowns, whose boxes reach the ground).
"""

from __future__ import annotations

import numpy as np
import pytest

from bench.results import record
from core.geometry import interpolate_pose, transform_points
from fixtures.simulate import Simulator
from logs.types import GroundTruthPose, LadarScan, ObjectBoxes, TransformFrame
from maps.stack import MapStack

POSE_BINS = 8
SOLID = {"building", "wall", "rock", "post", "bush", "vehicle", "person"}


def _pose_at(t: float, gt_t: np.ndarray, gt_T: np.ndarray) -> np.ndarray:
    i = int(np.clip(np.searchsorted(gt_t, t) - 1, 0, len(gt_t) - 2))
    a = float(np.clip((t - gt_t[i]) / (gt_t[i + 1] - gt_t[i]), 0.0, 1.0))
    return interpolate_pose(gt_T[i], gt_T[i + 1], a)


def _to_world(scan: LadarScan, T_body_ladar: np.ndarray, gt_t, gt_T) -> np.ndarray:
    """World points (N, 3) of a sweep, each slice of its firing time moved by its true pose."""
    off = scan.t_offset_ns
    edges = np.linspace(0, max(int(off.max()), 1), POSE_BINS + 1)
    which = np.clip(np.searchsorted(edges, off, side="right") - 1, 0, POSE_BINS - 1)
    out = np.empty(scan.points_xyz.shape)
    for b in range(POSE_BINS):
        sel = which == b
        t = scan.t_ns + 0.5 * (edges[b] + edges[b + 1])
        out[sel] = transform_points(_pose_at(t, gt_t, gt_T) @ T_body_ladar, scan.points_xyz[sel])
    return out


def _footprint_mask(xy: np.ndarray, boxes: list[tuple], grow_m: float) -> np.ndarray:
    """Mask: points (N, 2) inside the footprint of any box ``(centre (3,), size (3,), yaw)``,
    grown by ``grow_m`` (shrunk if negative)."""
    out = np.zeros(len(xy), dtype=bool)
    for centre, size, yaw in boxes:
        d = xy - centre[:2]
        c, s = np.cos(yaw), np.sin(yaw)
        u, v = d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c
        half = size[:2] / 2 + grow_m
        out |= (np.abs(u) <= half[0]) & (np.abs(v) <= half[1])
    return out


def _boxes(frame: ObjectBoxes, moving: bool, classes: set[str] | None = None) -> list[tuple]:
    """The (centre, size, yaw) of a frame's moving (or static) boxes of ``classes``."""
    speed = np.linalg.norm(frame.velocities, axis=1)
    return [
        (frame.centers[i], frame.sizes[i], frame.yaws[i])
        for i in range(len(frame))
        if (speed[i] > 0) == moving and (classes is None or frame.classes[i] in classes)
    ]


def occupancy_against_truth(seconds: float) -> dict[str, float]:
    """Run the default scenario for ``seconds``; score the 0.4 m level's occupancy."""
    sim = Simulator("default", seed=None)
    stacks = {"rays": MapStack(), "points": MapStack()}
    level = stacks["rays"].level("subsystem")
    res = level.resolution_m
    T_body_ladar = None
    gt_t: list[int] = []
    gt_T: list[np.ndarray] = []
    pending: list[LadarScan] = []
    static: ObjectBoxes | None = None
    moving: list[tuple] = []  # moving objects' boxes at every box frame
    for frame in sim.frames(seconds=seconds):
        if isinstance(frame, TransformFrame) and frame.child_frame_id == "ladar":
            T_body_ladar = frame.T_parent_child
        elif isinstance(frame, GroundTruthPose):
            gt_t.append(frame.t_ns)
            gt_T.append(frame.T_parent_child)
        elif isinstance(frame, LadarScan):
            pending.append(frame)
        elif isinstance(frame, ObjectBoxes):
            static = static or frame
            moving += _boxes(frame, moving=True)
        while pending and gt_t and gt_t[-1] >= pending[0].t_ns + int(pending[0].t_offset_ns.max()):
            scan = pending.pop(0)
            ts, Ts = np.asarray(gt_t, dtype=np.float64), np.asarray(gt_T)
            pts = _to_world(scan, T_body_ladar, ts, Ts)
            t_mid = scan.t_ns + 0.5 * float(scan.t_offset_ns.max())
            T_world_body = _pose_at(t_mid, ts, Ts)
            origin = (T_world_body @ T_body_ladar)[:3, 3]
            for name, stack in stacks.items():
                stack.move_to_pose(T_world_body)
                rays = origin if name == "rays" else None
                stack.fuse(pts, t_ns=scan.t_ns, sensor_xyz=origin, ray_origin_xyz=rays)
    rows, cols = np.indices((level.size, level.size)).reshape(2, -1)
    centres = level.window_to_world(rows, cols)
    occ = level.window("occupancy")[rows, cols]
    occ_points = stacks["points"].level("subsystem").window("occupancy")[rows, cols]
    on_object = _footprint_mask(centres, _boxes(static, False) + moving, 0.75 * res)
    solid = _footprint_mask(centres, _boxes(static, False, SOLID), -0.5 * res)
    occupied, free = occ > 0, occ < 0
    return {
        "occupied_on_objects": float(on_object[occupied].mean()),
        "free_in_solid_objects": float(solid[free].mean()),
        "solid_cells": int(solid.sum()),
        "solid_cells_free": int(free[solid].sum()),
        "solid_cells_free_points_only": int((occ_points < 0)[solid].sum()),
        "free_cells": int(free.sum()),
        "free_cells_points_only": int((occ_points < 0).sum()),
        "occupied_cells": int(occupied.sum()),
    }


def test_ray_casting_on_a_short_simulated_log() -> None:
    got = occupancy_against_truth(seconds=3.0)
    # rays add free space: a quarter again on ground as smooth as a field, whose returns
    # alone already mark most of it (twice as much on the rougher ground of simulators 1-8)
    assert got["free_cells"] > 1.15 * got["free_cells_points_only"]
    assert got["occupied_on_objects"] > 0.8
    assert got["free_in_solid_objects"] < 0.01


@pytest.mark.eval
def test_ray_casting_occupancy_on_simulated_default_log() -> None:
    got = occupancy_against_truth(seconds=30.0)
    cmd = "make eval"
    record(
        "maps_rays_occupied_cells_on_objects_0.4m",
        got["occupied_on_objects"],
        "fraction",
        target="> 0.8 (occupied cells within 0.3 m of a true object's footprint or under a "
        "moving agent's path)",
        command=cmd,
    )
    record(
        "maps_rays_free_cells_in_solid_objects_0.4m",
        got["free_in_solid_objects"],
        "fraction",
        target="< 0.01 (free cells more than 0.2 m inside a static solid object's footprint)",
        command=cmd,
    )
    record(
        "maps_rays_free_cells_0.4m",
        got["free_cells"],
        "cells",
        baseline="free cells without ray casting (ground points only)",
        baseline_value=got["free_cells_points_only"],
        target="reported (30 s of the default scenario)",
        command=cmd,
    )
    record(
        "maps_rays_solid_interior_cells_free_0.4m",
        got["solid_cells_free"],
        "cells",
        baseline="the same without ray casting",
        baseline_value=got["solid_cells_free_points_only"],
        target=f"reported (of {got['solid_cells']} cells more than 0.2 m inside static solid "
        "objects in the final window; low objects whose top is taken for ground are free "
        "either way)",
        command=cmd,
    )
    assert got["occupied_on_objects"] > 0.8
    assert got["free_in_solid_objects"] < 0.01
