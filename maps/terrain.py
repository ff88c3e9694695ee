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


def update_terrain(level: MapLevel, config: TerrainConfig | None = None) -> None:
    """Recompute slope, step_height and traversability over the whole window of ``level``
    (one compiled pass, :func:`maps.kernels.terrain`; its numpy form is the test oracle
    ``terrain_layers_reference`` in ``tests/kernel_reference/terrain_reference.py``)."""
    config = config or TerrainConfig()
    level.require(*TERRAIN_LAYERS)
    e = level.window("elevation").astype(np.float64)
    rough = level.window("roughness").astype(np.float64)
    occ = level.window("occupancy").astype(np.float64)
    out = [np.empty(e.shape, dtype=np.float32) for _ in range(3)]
    kernels.terrain(
        e, rough, occ, level.resolution_m, config.max_slope_rad, config.max_step_m,
        config.max_roughness_m, config.occupied_log_odds, *out,
    )  # fmt: skip
    slope, step, trav = out
    level.set_window("slope", slope)
    level.set_window("step_height", step)
    level.set_window("traversability", trav)
