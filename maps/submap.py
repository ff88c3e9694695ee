"""Submap selections: the window cells inside a box, circle or polygon, or along a line.

Each function takes a :class:`~maps.level.MapLevel` and world-frame shapes in metres, and
returns ``(rows, cols)``: int64 window indices (row = y, col = x; see :mod:`maps.level`) of
the selected cells, in row-major order, clipped to the window. A cell is selected when its
centre is inside the shape (box, circle, polygon) or when the line passes through it.
Read values with ``level.window(name)[rows, cols]`` or via
``level.storage(name)[level.window_to_storage(rows, cols)]``.
"""

from __future__ import annotations

import numpy as np

from core.errors import EngineError
from maps.level import MapLevel


class SubmapError(EngineError, ValueError):
    """A selection shape that is not what the function takes (names the value)."""


def box(level: MapLevel, xy_min: np.ndarray, xy_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells whose centres lie in the axis-aligned world box ``[xy_min, xy_max]``."""
    lo, hi = _point(xy_min, "xy_min"), _point(xy_max, "xy_max")
    if np.any(hi < lo):
        raise SubmapError(f"box xy_max {hi.tolist()} is below xy_min {lo.tolist()}")
    return _centres_where(level, lo, hi, lambda c: np.ones(len(c), dtype=bool))


def circle(
    level: MapLevel, center_xy: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Cells whose centres lie within ``radius_m`` of world point ``center_xy``."""
    c0 = _point(center_xy, "center_xy")
    if not (np.isfinite(radius_m) and radius_m >= 0):
        raise SubmapError(f"circle radius_m must be finite and >= 0, got {radius_m!r}")
    r2 = float(radius_m) ** 2
    return _centres_where(
        level, c0 - radius_m, c0 + radius_m, lambda c: ((c - c0) ** 2).sum(axis=1) <= r2
    )


def inside_polygon(xy: np.ndarray, vertices_xy: np.ndarray) -> np.ndarray:
    """(N,) bool: which points ``xy`` (N, 2) lie inside the simple polygon ``vertices_xy``
    (K, 2), same units. Even-odd crossing rule, one vectorised pass per edge (memory O(N))."""
    x, y = xy[:, 0], xy[:, 1]
    inside = np.zeros(len(xy), dtype=bool)
    for (x0, y0), (x1, y1) in zip(vertices_xy, np.roll(vertices_xy, -1, axis=0), strict=True):
        if y0 == y1:
            continue  # a horizontal edge is never crossed by the horizontal ray
        straddles = (y0 > y) != (y1 > y)
        inside ^= straddles & (x < x0 + (y - y0) * (x1 - x0) / (y1 - y0))
    return inside


def polygon(level: MapLevel, vertices_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells whose centres lie inside the simple polygon ``vertices_xy`` (K >= 3, 2) metres
    (:func:`inside_polygon`)."""
    v = np.asarray(vertices_xy, dtype=np.float64)
    if v.ndim != 2 or v.shape[0] < 3 or v.shape[1] != 2 or not np.all(np.isfinite(v)):
        raise SubmapError(f"polygon needs (K >= 3, 2) finite vertices, got shape {v.shape}")
    return _centres_where(level, v.min(axis=0), v.max(axis=0), lambda c: inside_polygon(c, v))


def line(level: MapLevel, p0_xy: np.ndarray, p1_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells the segment ``p0 -> p1`` (world metres) passes through, ordered from ``p0``.

    Sampled at a quarter cell, so every cell the segment crosses by more than a corner is
    listed once.
    """
    a, b = _point(p0_xy, "p0_xy"), _point(p1_xy, "p1_xy")
    n = max(2, int(np.ceil(np.linalg.norm(b - a) / (0.25 * level.resolution_m))) + 1)
    pts = a[None] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None]
    rows, cols, inside = level.world_to_window(pts)
    rows, cols = rows[inside], cols[inside]
    keep = np.ones(rows.shape, dtype=bool)
    keep[1:] = (rows[1:] != rows[:-1]) | (cols[1:] != cols[:-1])
    return rows[keep], cols[keep]


def _centres_where(level: MapLevel, lo: np.ndarray, hi: np.ndarray, test) -> tuple:
    """Window cells whose centres are in the box ``[lo, hi]`` and pass ``test(centres)``."""
    res, size = level.resolution_m, level.size
    c_lo = np.ceil(lo / res - 0.5).astype(np.int64) - level.origin_cell
    c_hi = np.floor(hi / res - 0.5).astype(np.int64) - level.origin_cell
    c_lo, c_hi = np.clip(c_lo, 0, size), np.clip(c_hi, -1, size - 1)
    cols = np.arange(c_lo[0], c_hi[0] + 1)
    rows = np.arange(c_lo[1], c_hi[1] + 1)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    rr, cc = rr.ravel(), cc.ravel()
    keep = test(level.window_to_world(rr, cc)) if rr.size else np.zeros(0, dtype=bool)
    return rr[keep], cc[keep]


def _point(p: np.ndarray, what: str) -> np.ndarray:
    q = np.asarray(p, dtype=np.float64).reshape(-1)
    if q.shape[0] < 2 or not np.all(np.isfinite(q[:2])):
        raise SubmapError(f"{what} must be a finite (x, y) in metres, got {q.tolist()}")
    return q[:2]
