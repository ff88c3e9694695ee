"""Numpy oracle of the compiled terrain pass of :mod:`maps.terrain` (tests only).

:func:`terrain_layers_reference` is the oracle of :func:`maps.kernels.terrain` (behind
:func:`maps.terrain.update_terrain`): slope from central differences (one-sided beside an
unknown cell or the window's edge), step height (:func:`maps.terrain.step_heights`, which the
engine also uses for map registration) and traversability, in float64 over the window.
"""

from __future__ import annotations

import numpy as np

from maps.terrain import TerrainConfig, step_heights


def _gradient(prev: np.ndarray, centre: np.ndarray, nxt: np.ndarray, res: float) -> np.ndarray:
    """Height gradient (m/m) along one axis: the central difference where both neighbours are
    known, else the one-sided difference with the known one; NaN where both neighbours are
    unknown (the caller masks unknown cells)."""
    with np.errstate(invalid="ignore"):
        g = (nxt - prev) / (2.0 * res)
        g = np.where(np.isfinite(g), g, (nxt - centre) / res)
        return np.where(np.isfinite(g), g, (centre - prev) / res)


def terrain_layers_reference(
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
