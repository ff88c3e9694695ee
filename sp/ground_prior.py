"""The ground the world model expects: a prior for SP's ground segmentation of far returns.

Reference 001, 4.5.4 and 4.6 (sensory processing compares what it observes with what the world
model predicts; the world model's maps hold the terrain, 4.4.10). A return far out is often the
only one its column has on an object (a car's roof seen over nearer cars, the top of a low rock
one row above the ground): the column walk (:mod:`sp.ground`) then sees a gentle rise from the
last ground return and calls it ground. The terrain map already knows the ground around it,
fused from nearer views in earlier sweeps. A far return standing well above the lowest ground
the map knows nearby is not ground.

The map is given as its storage: a toroidal (n, n) grid of ground heights, world z in metres,
NaN where unknown; cell ``(ix, iy)`` (``ix = floor(x / resolution_m)``) lives at
``[iy % n, ix % n]`` and is in the window when ``origin_cell <= (ix, iy) < origin_cell + n``
(the convention of :mod:`maps.level`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import EngineError


class GroundPriorError(EngineError, ValueError):
    """A ground prior SP cannot use; names the value."""


@dataclass(frozen=True)
class GroundPriorConfig:
    """How SP uses the world model's ground (metres, degrees).

    min_range_m:  only returns at least this far (horizontal range from the sensor) are checked;
                  nearer, the rows lie close enough for the column walk alone.
    above_m:      a ground return more than this above the expected ground is not ground:
                  above a curb, a bank or the envelope's slope allowance, below a car's roof
                  (1.3-1.6 m). Lower (0.5 m, the height of a low rock) also took people's
                  legs far out off the ground, and pairs of people walking side by side were
                  then joined and tracked as one vehicle more often (development seeds).
    radius_m:     the expected ground at a point is the lowest known ground within this
                  distance of it, each cell raised by ``slope_deg`` over its distance (a slope
                  is not taken for an object; a car's roof is judged against the ground
                  beside it, not the roof the map may have fused as ground when it saw
                  nothing lower).
    """

    enabled: bool = True
    min_range_m: float = 15.0
    above_m: float = 0.8
    radius_m: float = 2.0
    slope_deg: float = 15.0

    def __post_init__(self) -> None:
        if not (self.min_range_m >= 0 and self.above_m > 0 and self.radius_m >= 0):
            raise GroundPriorError(
                f"ground prior min_range_m {self.min_range_m}, above_m {self.above_m}, "
                f"radius_m {self.radius_m}: need >= 0, > 0, >= 0"
            )
        if not 0 <= self.slope_deg < 80:
            raise GroundPriorError(f"ground prior slope_deg {self.slope_deg} is not in [0, 80)")


@dataclass(frozen=True)
class GroundPrior:
    """Ground heights the world model expects (module docstring for the grid convention).

    z_m:          (n, n) float world z of the ground (m), NaN unknown; toroidal storage.
    origin_cell:  (ix0, iy0) the window's lowest cell.
    resolution_m: cell edge (m).
    """

    z_m: np.ndarray
    origin_cell: tuple[int, int]
    resolution_m: float

    def __post_init__(self) -> None:
        z = np.asarray(self.z_m)
        if z.ndim != 2 or z.shape[0] != z.shape[1] or z.shape[0] < 1:
            raise GroundPriorError(f"ground prior grid has shape {z.shape}; needs (n, n)")
        if not self.resolution_m > 0:
            raise GroundPriorError(f"ground prior resolution_m {self.resolution_m} is not > 0")

    def expected(self, xy_m: np.ndarray, radius_m: float, slope_tan: float) -> np.ndarray:
        """(N,) float64 expected ground height (world z, m) at world points ``xy_m`` (N, 2):
        the minimum over known cells whose centre lies within ``radius_m`` of the point's cell
        centre of (height + ``slope_tan`` x distance); NaN where no such cell is known."""
        xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
        out = np.full(len(xy), np.nan)
        if not len(xy):
            return out
        n, res = self.z_m.shape[0], float(self.resolution_m)
        cell = np.floor(xy / res).astype(np.int64)
        # the same cell is asked for by many returns: work per distinct cell
        cells, inverse = np.unique(cell, axis=0, return_inverse=True)
        best = np.full(len(cells), np.inf)
        k = int(radius_m // res)
        ix0, iy0 = self.origin_cell
        for dy in range(-k, k + 1):
            for dx in range(-k, k + 1):
                d = res * float(np.hypot(dx, dy))
                if d > radius_m:
                    continue
                cx, cy = cells[:, 0] + dx, cells[:, 1] + dy
                inside = (cx >= ix0) & (cx < ix0 + n) & (cy >= iy0) & (cy < iy0 + n)
                z = np.full(len(cells), np.nan)
                z[inside] = self.z_m[cy[inside] % n, cx[inside] % n]
                np.fmin(best, z + slope_tan * d, out=best)
        best[~np.isfinite(best)] = np.nan
        out[:] = best[inverse.reshape(-1)]
        return out


def not_ground(
    xyz_w: np.ndarray,
    range_m: np.ndarray,
    ground: np.ndarray,
    prior: GroundPrior,
    config: GroundPriorConfig,
) -> np.ndarray:
    """(H, W) bool: the ``ground`` pixels (H, W) bool at horizontal range ``range_m`` (H, W) m
    of at least ``min_range_m`` whose world point ``xyz_w`` (H, W, 3) m lies more than
    ``above_m`` above the ground ``prior`` expects there."""
    far = ground & (range_m >= config.min_range_m)
    out = np.zeros(ground.shape, dtype=bool)
    if not far.any():
        return out
    p = xyz_w[far]
    z0 = prior.expected(p[:, :2], config.radius_m, float(np.tan(np.radians(config.slope_deg))))
    out[far] = p[:, 2] - z0 > config.above_m  # NaN (no prior) compares False
    return out
