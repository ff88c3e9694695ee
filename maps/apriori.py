"""A priori elevation rasters (digital terrain maps) and writing them into map levels.

Reference 001, 4.4.7: a priori maps are coarse (elevation postings every 30 m, sometimes 1-3 m)
and feed the coarse end of the map hierarchy; local maps built from sensors are registered
with them and refine them.

A raster is a 2-D array of heights with an affine map from world ``(x, y)`` to pixel
``(col, row)``: ``[col, row] = A @ [x, y, 1]``; pixel ``(row, col)`` covers
``[col, col+1) x [row, row+1)`` in pixel coordinates (the Argoverse 2 convention:
``pixel = s * (R @ xy + t)``, truncated).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.errors import EngineError
from maps.level import MapLevel


class AprioriError(EngineError, ValueError):
    """A raster file or array that cannot be used as a priori terrain (names it)."""


@dataclass(frozen=True)
class ElevationRaster:
    """Heights ``(H, W)`` float64 metres (NaN = no data) and ``A_pixel_world`` (2, 3)."""

    heights_m: np.ndarray
    A_pixel_world: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        h = np.asarray(self.heights_m)
        if h.ndim != 2 or min(h.shape) < 1:
            raise AprioriError(f"raster {self.source!r}: heights must be (H, W), got {h.shape}")
        A = np.asarray(self.A_pixel_world, dtype=np.float64)
        if A.shape != (2, 3) or not np.all(np.isfinite(A)) or abs(np.linalg.det(A[:, :2])) < 1e-12:
            raise AprioriError(
                f"raster {self.source!r}: A_pixel_world must be an invertible (2, 3)"
            )

    @property
    def pixel_size_m(self) -> float:
        """Edge of one pixel in metres (assumes square pixels)."""
        return float(1.0 / np.sqrt(abs(np.linalg.det(self.A_pixel_world[:, :2]))))

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """World ``(N, 2)`` -> continuous pixel coordinates ``(N, 2)`` as ``(col, row)``."""
        xy = np.asarray(xy, dtype=np.float64)[:, :2]
        return xy @ self.A_pixel_world[:, :2].T + self.A_pixel_world[:, 2]

    def pixel_to_world(self, colrow: np.ndarray) -> np.ndarray:
        """Continuous pixel ``(N, 2)`` ``(col, row)`` -> world ``(N, 2)``."""
        M = self.A_pixel_world[:, :2]
        return (np.asarray(colrow, dtype=np.float64) - self.A_pixel_world[:, 2]) @ np.linalg.inv(
            M
        ).T

    def sample(self, xy: np.ndarray) -> np.ndarray:
        """Height of the pixel holding each world point ``(N, 2)``; NaN off the raster."""
        cr = np.floor(self.world_to_pixel(xy)).astype(np.int64)
        h, w = self.heights_m.shape
        ok = (cr[:, 0] >= 0) & (cr[:, 0] < w) & (cr[:, 1] >= 0) & (cr[:, 1] < h)
        out = np.full(cr.shape[0], np.nan)
        out[ok] = self.heights_m[cr[ok, 1], cr[ok, 0]]
        return out

    def shifted(self, offset_xy_m: np.ndarray) -> ElevationRaster:
        """The same heights placed ``offset_xy_m`` further along world x, y."""
        A = self.A_pixel_world.copy()
        A[:, 2] -= A[:, :2] @ np.asarray(offset_xy_m, dtype=np.float64)
        return ElevationRaster(self.heights_m, A, self.source)


def load_av2_ground_height(map_dir: str | Path) -> ElevationRaster:
    """The Argoverse 2 ground-height raster of a log map folder (``*ground_height_surface*.npy``
    with its ``*Sim2_city.json``: pixel = s * (R @ city_xy + t)); world frame = city frame."""
    d = Path(map_dir)
    npys = sorted(d.glob("*ground_height_surface*.npy"))
    sims = sorted(d.glob("*Sim2_city.json"))
    if not npys or not sims:
        raise AprioriError(
            f"{d}: need *ground_height_surface*.npy and *Sim2_city.json, found "
            f"{[p.name for p in d.iterdir()] if d.is_dir() else 'no folder'}"
        )
    heights = np.load(npys[0]).astype(np.float64)
    sim = json.loads(sims[0].read_text())
    try:
        R = np.asarray(sim["R"], dtype=np.float64).reshape(2, 2)
        t = np.asarray(sim["t"], dtype=np.float64).reshape(2)
        s = float(sim["s"])
    except (KeyError, ValueError) as exc:
        raise AprioriError(f"{sims[0]}: not a Sim(2) with R (4), t (2), s: {sim}") from exc
    A = np.hstack([s * R, (s * t)[:, None]])
    return ElevationRaster(heights, A, str(npys[0]))


def write_raster(
    level: MapLevel,
    raster: ElevationRaster,
    variance_m2: float,
    rows: np.ndarray | None = None,
    cols: np.ndarray | None = None,
    only_empty: bool = True,
    max_samples_per_axis: int = 4,
) -> int:
    """Write the raster's mean height over each cell into ``level`` as a prior estimate.

    Cells are the window cells ``(rows, cols)`` (all by default); with ``only_empty`` cells
    that already hold an elevation are left alone. Each cell averages the raster at up to
    ``max_samples_per_axis^2`` points spread over it. The prior enters as ``elevation`` with
    ``elevation_var = variance_m2``; later points refine it by the usual Kalman update.
    Returns the number of cells written.
    """
    level.require("elevation", "elevation_var")
    if rows is None or cols is None:
        rr, cc = np.meshgrid(np.arange(level.size), np.arange(level.size), indexing="ij")
        rows, cols = rr.ravel(), cc.ravel()
    srow, scol = level.window_to_storage(rows, cols)
    elev = level.storage("elevation")
    if only_empty:
        empty = np.isnan(elev[srow, scol])
        rows, cols, srow, scol = rows[empty], cols[empty], srow[empty], scol[empty]
    if rows.size == 0:
        return 0
    n = int(np.clip(np.ceil(level.resolution_m / raster.pixel_size_m), 1, max_samples_per_axis))
    frac = (np.arange(n) + 0.5) / n - 0.5
    du, dv = np.meshgrid(frac, frac, indexing="ij")
    centres = level.window_to_world(rows, cols)
    pts = centres[:, None, :] + level.resolution_m * np.stack([du.ravel(), dv.ravel()], -1)[None]
    heights = raster.sample(pts.reshape(-1, 2)).reshape(len(rows), n * n)
    good = np.isfinite(heights)
    cnt = good.sum(axis=1)
    mean = np.where(good, heights, 0.0).sum(axis=1) / np.maximum(cnt, 1)
    ok = cnt > 0
    cell = (srow[ok], scol[ok])
    elev[cell] = mean[ok]
    level.storage("elevation_var")[cell] = variance_m2
    return int(np.count_nonzero(ok))
