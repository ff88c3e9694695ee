"""Region shapes and a grid index over entity positions (sorted cell keys, pure numpy).

Positions are binned into square cells of ``cell_m`` metres on the frame's x-y plane; the
index keeps the cell keys sorted, so a query visits one contiguous key range per cell column
(``searchsorted``) and tests only the candidates it finds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kd_store.errors import KDError

_OFFSET = 1 << 31  # shift signed cell coordinates into non-negative 32-bit halves


@dataclass(frozen=True, slots=True)
class Box:
    """Axis-aligned box in frame ``frame``: ``min_xyz`` <= p <= ``max_xyz`` (metres)."""

    frame: str
    min_xyz: tuple[float, float, float]
    max_xyz: tuple[float, float, float]

    def bounds_xy(self) -> tuple[float, float, float, float]:
        return (self.min_xyz[0], self.min_xyz[1], self.max_xyz[0], self.max_xyz[1])

    def contains(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) -> (N,) bool."""
        return np.all((p >= np.asarray(self.min_xyz)) & (p <= np.asarray(self.max_xyz)), axis=1)


@dataclass(frozen=True, slots=True)
class Circle:
    """Disc of ``radius_m`` around ``center_xy`` in frame ``frame``, any height."""

    frame: str
    center_xy: tuple[float, float]
    radius_m: float

    def bounds_xy(self) -> tuple[float, float, float, float]:
        (x, y), r = self.center_xy, self.radius_m
        return (x - r, y - r, x + r, y + r)

    def contains(self, p: np.ndarray) -> np.ndarray:
        d = p[:, :2] - np.asarray(self.center_xy)
        return np.einsum("ij,ij->i", d, d) <= self.radius_m**2


Region = Box | Circle


def check_region(region: Region) -> None:
    lo_x, lo_y, hi_x, hi_y = region.bounds_xy()
    vals = np.array([lo_x, lo_y, hi_x, hi_y], dtype=np.float64)
    if not np.all(np.isfinite(vals)) or lo_x > hi_x or lo_y > hi_y:
        raise KDError(f"region {region!r} is empty or not finite")
    if isinstance(region, Box) and region.min_xyz[2] > region.max_xyz[2]:
        raise KDError(f"region {region!r}: min z above max z")


class GridIndex:
    """Slots (ints) by x-y cell. Build once from arrays; rebuild when positions change."""

    def __init__(self, slots: np.ndarray, positions_xyz: np.ndarray, cell_m: float) -> None:
        """slots: (N,) int64; positions_xyz: (N, 3) float64 metres."""
        self.cell_m = float(cell_m)
        keys = self._keys(positions_xyz[:, 0], positions_xyz[:, 1])
        order = np.argsort(keys, kind="stable")
        self.keys = keys[order]
        self.slots = slots[order]

    def _cell(self, v: np.ndarray) -> np.ndarray:
        return np.floor(v / self.cell_m).astype(np.int64) + _OFFSET

    def _keys(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return (self._cell(x) << 32) | self._cell(y)

    def candidates(self, region: Region) -> np.ndarray:
        """Slots in the cells the region's x-y bounds touch (a superset of the answer)."""
        lo_x, lo_y, hi_x, hi_y = region.bounds_xy()
        cx0, cx1 = self._cell(np.array([lo_x, hi_x]))
        cy0, cy1 = self._cell(np.array([lo_y, hi_y]))
        cols = np.arange(cx0, cx1 + 1, dtype=np.int64) << 32
        starts = np.searchsorted(self.keys, cols | cy0, side="left")
        ends = np.searchsorted(self.keys, cols | cy1, side="right")
        if len(starts) == 1:
            return self.slots[starts[0] : ends[0]]
        return np.concatenate([self.slots[s:e] for s, e in zip(starts, ends, strict=True)])
