"""Scores against a log's ground truth: odometry error and elevation RMSE (what ``wm run`` reports
beside the tracking scores of :mod:`wm.evaluation` when the log carries truth), and the truth
helpers both use.

Truth comes from the log itself: ``/ground_truth/pose`` (GroundTruthPose), ``/ground_truth/
objects`` (ObjectBoxes) and the simulator's ``terrain.npy`` attachment with its ``terrain``
metadata (origin_x, origin_y, resolution_m; heights[row, col] at
``(origin_x + col * res, origin_y + row * res)``, world frame).
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.geometry import se3_inverse
from logs.types import ObjectBoxes
from maps.apriori import ElevationRaster, load_av2_ground_height
from maps.level import MapLevel
from wm.poses import PoseError, PoseTrack


@dataclass(frozen=True)
class TerrainTruth:
    """True terrain heights (rows, cols) float64 m on a regular world grid."""

    heights: np.ndarray
    origin_xy: tuple[float, float]
    resolution_m: float

    @classmethod
    def from_log(cls, attachments: dict[str, bytes], metadata: dict) -> TerrainTruth | None:
        meta = metadata.get("terrain")
        if "terrain.npy" not in attachments or not meta:
            return None
        h = np.load(io.BytesIO(attachments["terrain.npy"])).astype(np.float64)
        if h.ndim != 2 or min(h.shape) < 2:
            raise ValueError(f"terrain.npy holds an array of shape {h.shape}, not a grid")
        origin = (float(meta["origin_x"]), float(meta["origin_y"]))
        return cls(h, origin, float(meta["resolution_m"]))

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Bilinear height (N,) at world points (N, 2); NaN off the grid."""
        u = (xy[:, 0] - self.origin_xy[0]) / self.resolution_m
        v = (xy[:, 1] - self.origin_xy[1]) / self.resolution_m
        rows, cols = self.heights.shape
        ok = (u >= 0) & (v >= 0) & (u <= cols - 1) & (v <= rows - 1)
        j = np.clip(np.floor(u).astype(np.int64), 0, cols - 2)
        i = np.clip(np.floor(v).astype(np.int64), 0, rows - 2)
        fx, fy = np.clip(u - j, 0, 1), np.clip(v - i, 0, 1)
        g = self.heights
        h = (g[i, j] * (1 - fx) + g[i, j + 1] * fx) * (1 - fy) + (
            g[i + 1, j] * (1 - fx) + g[i + 1, j + 1] * fx
        ) * fy
        return np.where(ok, h, np.nan)


@dataclass(frozen=True)
class RasterTruth:
    """A real ground-height raster as terrain truth (e.g. Argoverse 2's ground surface)."""

    raster: ElevationRaster

    @classmethod
    def from_folder(cls, folder: Path) -> RasterTruth | None:
        """The AV2 map's ground-height raster when ``folder`` is an AV2 log that has one."""
        map_dir = folder / "map"
        if not (folder.is_dir() and any(map_dir.glob("*ground_height_surface*.npy"))):
            return None
        try:
            return cls(load_av2_ground_height(map_dir))
        except (OSError, ValueError):
            return None

    def height(self, xy: np.ndarray) -> np.ndarray:
        return self.raster.sample(xy)


def elevation_error(
    level: MapLevel, truth: TerrainTruth | RasterTruth, T_true_est: np.ndarray | None = None
) -> dict[str, float]:
    """The level's elevation over ground cells (points fused, none above the ground estimate)
    against the truth at cell centres: RMSE (m), median |error| (m; robust to the tops of
    objects seen from one side only, which pass for ground) and the number of cells.

    ``T_true_est`` (4x4), when given, maps the map's (estimated) world frame into the true one,
    e.g. the pose error at the last sweep ``T_world_body_true @ inv(T_world_body_est)``: the
    cells are moved by it before comparing, so the figure scores the local map rather than
    the odometry's accumulated drift."""
    count = level.window("count")
    obst = level.window("obstacle_count")
    rows, cols = np.nonzero((count > 0) & (obst == 0))
    if not len(rows):
        return {"rmse_m": float("nan"), "median_abs_m": float("nan"), "cells": 0}
    est = level.window("elevation")[rows, cols].astype(np.float64)
    xy = level.window_to_world(rows, cols)
    if T_true_est is not None:
        p = np.column_stack([xy, est]) @ T_true_est[:3, :3].T + T_true_est[:3, 3]
        xy, est = p[:, :2], p[:, 2]
    true = truth.height(xy)
    ok = np.isfinite(est) & np.isfinite(true)
    if not ok.any():
        return {"rmse_m": float("nan"), "median_abs_m": float("nan"), "cells": 0}
    e = est[ok] - true[ok]
    return {
        "rmse_m": float(np.sqrt(np.mean(e**2))),
        "median_abs_m": float(np.median(np.abs(e))),
        "cells": int(ok.sum()),
    }


@dataclass
class OdometryScore:
    """Position error (m) of the node's poses against the truth at each sweep, the estimated
    world aligned to the true one at the first scored pose (evo's ``align_origin``): the
    odometry starts its own world and never sees the truth, so only motion since the first
    sweep is scored. ``T_true_est`` maps the estimated world into the true one by the pose
    error of the last sweep (the drift, for local map scores)."""

    errors_m: list[float] = field(default_factory=list)
    path_m: float = 0.0
    T_true_est: np.ndarray | None = None
    T_align: np.ndarray | None = None  # true world <- estimated world, at the first pose
    _last_xy: np.ndarray | None = None

    def add(self, t_ns: int, T_world_body: np.ndarray, truth: PoseTrack) -> None:
        try:
            T_true = truth.at(t_ns)
        except PoseError:
            return
        if self.T_align is None:
            self.T_align = T_true @ se3_inverse(T_world_body)
        T_aligned = self.T_align @ T_world_body
        self.errors_m.append(float(np.linalg.norm(T_aligned[:3, 3] - T_true[:3, 3])))
        self.T_true_est = T_true @ se3_inverse(T_world_body)  # the pose error at this sweep
        if self._last_xy is not None:
            self.path_m += float(np.linalg.norm(T_true[:2, 3] - self._last_xy))
        self._last_xy = T_true[:2, 3].copy()

    def summary(self) -> dict[str, float]:
        if not self.errors_m:
            return {}
        e = np.asarray(self.errors_m)
        return {
            "ate_rmse_m": float(np.sqrt(np.mean(e**2))),
            "final_error_m": float(e[-1]),
            "path_m": self.path_m,
            "final_error_pct_of_path": float(100 * e[-1] / self.path_m) if self.path_m else 0.0,
        }


#: Argoverse 2 categories (and other datasets' names) as the engine's classes, for scoring.
CLASS_ALIASES: dict[str, str] = {
    "REGULAR_VEHICLE": "vehicle", "LARGE_VEHICLE": "vehicle", "BUS": "vehicle",
    "BOX_TRUCK": "vehicle", "TRUCK": "vehicle", "TRUCK_CAB": "vehicle",
    "VEHICULAR_TRAILER": "vehicle",
    "SCHOOL_BUS": "vehicle", "ARTICULATED_BUS": "vehicle", "MOTORCYCLE": "vehicle",
    "PEDESTRIAN": "person", "BICYCLIST": "person", "MOTORCYCLIST": "person",
    "WHEELED_RIDER": "person", "BOLLARD": "post", "SIGN": "post", "STOP_SIGN": "post",
    "CONSTRUCTION_CONE": "post", "CONSTRUCTION_BARREL": "post",
}  # fmt: skip


def truth_boxes_to_world(boxes: ObjectBoxes, T_world_frame: np.ndarray) -> ObjectBoxes:
    """Boxes given in a moving frame, moved to the world with that frame's pose (4x4)."""
    R, t = T_world_frame[:3, :3], T_world_frame[:3, 3]
    yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    return ObjectBoxes(
        boxes.t_ns, "world", boxes.ids,
        [CLASS_ALIASES.get(c, c) for c in boxes.classes],
        boxes.centers @ R.T + t, boxes.sizes, boxes.yaws + yaw,
        np.nan_to_num(boxes.velocities) @ R.T, boxes.topic, boxes.n_returns,
    )  # fmt: skip
