"""Terrain layers derived from the elevation of neighbouring cells: slope, step height,
traversability (reference 001, 4.4.7: map pixels may hold "terrain roughness, slope, and
traversability").

Computed in window order (so the toroidal seam never makes two far cells neighbours) and
written back. Cells with no elevation, or whose neighbours have none, stay NaN. Slope is the
angle of the height gradient, from central differences, one-sided beside an unknown cell or
the window's edge (so a steep cell next to a hole still counts as steep).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from maps import kernels
from maps.level import MapLevel

TERRAIN_LAYERS = ("elevation", "roughness", "occupancy", "slope", "step_height", "traversability")


@dataclass(frozen=True)
class TerrainConfig:
    """Limits at which a cell becomes impassable: slope (rad), step (m), roughness (m)."""

    max_slope_rad: float = 0.5
    max_step_m: float = 0.3
    max_roughness_m: float = 0.15
    occupied_log_odds: float = 1.0  # at or above this occupancy a cell is impassable
    compiled: bool = True  # one compiled pass (maps.kernels.terrain); False: the numpy form


def step_heights(elevation: np.ndarray) -> np.ndarray:
    """Largest absolute height difference (m) of each cell to its 8 neighbours (H, W), in
    window order; NaN where the cell or all its neighbours are unknown."""
    e = np.asarray(elevation, dtype=np.float64)
    step = np.full(e.shape, np.nan)
    # each neighbour pair's difference once (|a - b| == |b - a|), given to both cells
    pairs = (
        ((slice(None), slice(1, None)), (slice(None), slice(None, -1))),  # right
        ((slice(1, None), slice(None)), (slice(None, -1), slice(None))),  # down
        ((slice(1, None), slice(1, None)), (slice(None, -1), slice(None, -1))),  # down-right
        ((slice(1, None), slice(None, -1)), (slice(None, -1), slice(1, None))),  # down-left
    )
    with np.errstate(invalid="ignore"):
        for a, b in pairs:
            d = np.abs(e[a] - e[b])
            np.fmax(step[a], d, out=step[a])
            np.fmax(step[b], d, out=step[b])
    return step


def _gradient(prev: np.ndarray, centre: np.ndarray, nxt: np.ndarray, res: float) -> np.ndarray:
    """Height gradient (m/m) along one axis: the central difference where both neighbours are
    known, else the one-sided difference with the known one; NaN where both neighbours are
    unknown (the caller masks unknown cells)."""
    with np.errstate(invalid="ignore"):
        g = (nxt - prev) / (2.0 * res)
        g = np.where(np.isfinite(g), g, (nxt - centre) / res)
        return np.where(np.isfinite(g), g, (centre - prev) / res)


def update_terrain(level: MapLevel, config: TerrainConfig | None = None) -> None:
    """Recompute slope, step_height and traversability over the whole window of ``level``
    (one compiled pass, :func:`maps.kernels.terrain`; ``config.compiled`` False: the numpy
    form, :func:`terrain_layers`, which the tests compare it with)."""
    config = config or TerrainConfig()
    level.require(*TERRAIN_LAYERS)
    e = level.window("elevation").astype(np.float64)
    rough = level.window("roughness").astype(np.float64)
    occ = level.window("occupancy").astype(np.float64)
    if config.compiled:
        out = [np.empty(e.shape, dtype=np.float32) for _ in range(3)]
        kernels.terrain(
            e, rough, occ, level.resolution_m, config.max_slope_rad, config.max_step_m,
            config.max_roughness_m, config.occupied_log_odds, *out,
        )  # fmt: skip
        slope, step, trav = out
    else:
        slope, step, trav = (
            a.astype(np.float32) for a in terrain_layers(e, rough, occ, level.resolution_m, config)
        )
    level.set_window("slope", slope)
    level.set_window("step_height", step)
    level.set_window("traversability", trav)


def terrain_layers(
    e: np.ndarray, rough: np.ndarray, occ: np.ndarray, res: float, config: TerrainConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slope (rad), step height (m) and traversability (0..1) (H, W) float64 of a window of
    elevation ``e`` (m, NaN unknown), roughness (m) and occupancy (log-odds); cell ``res`` m."""
    pad = np.pad(e, 1, constant_values=np.nan)
    gx = _gradient(pad[1:-1, :-2], e, pad[1:-1, 2:], res)
    gy = _gradient(pad[:-2, 1:-1], e, pad[2:, 1:-1], res)
    # a slope known along one axis only is a lower bound, better than none: a steep cell next
    # to a hole must not look passable
    known = np.isfinite(gx) | np.isfinite(gy)
    known &= np.isfinite(e)  # the central difference skips the cell: an unknown stays NaN
    slope = np.where(known, np.arctan(np.hypot(np.nan_to_num(gx), np.nan_to_num(gy))), np.nan)
    step = step_heights(e)
    badness = np.fmax(
        np.fmax(slope / config.max_slope_rad, step / config.max_step_m),
        rough / config.max_roughness_m,
    )
    trav = np.clip(1.0 - badness, 0.0, 1.0)
    trav[occ >= config.occupied_log_odds] = 0.0
    trav[~np.isfinite(e)] = np.nan
    return slope, step, trav
