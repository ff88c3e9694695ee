"""Numpy oracle of the compiled binning of :mod:`sp.egosphere` (tests only).

:func:`to_egosphere_reference` is the oracle of :func:`sp.egosphere.to_egosphere`: each point's
pixel by :func:`_pixel_of` (column from numpy's arctan2 of the azimuth, row from the ring or
the elevation; points nearer than ``min_range_m`` or outside the rows dropped), then each
pixel's nearest returns, layer by layer, ties to the lower point index (:func:`_nearest`). The
kernel must give the same image bit for bit.
"""

from __future__ import annotations

import sys

import numpy as np

from core.geometry import check_pose
from logs.types import LadarScan
from sp.egosphere import EgosphereConfig, EgosphereImage, check_scan


def _pixel_of(
    scan: LadarScan,
    config: EgosphereConfig,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    horiz2: np.ndarray,
    range_m: np.ndarray,
) -> np.ndarray:
    """Flat pixel index (N,) int64 of every point; -1 for points that are dropped."""
    col = ((np.pi - np.arctan2(y, x)) * np.float32(config.n_cols / (2 * np.pi))).astype(np.int32)
    np.clip(col, 0, config.n_cols - 1, out=col)
    if config.use_ring and scan.ring is not None:
        ring = scan.ring.astype(np.int32)
        row = config.n_rows - 1 - ring if config.ring_zero_at_bottom else ring
        ok = (row >= 0) & (row < config.n_rows)
    else:
        el_hi = np.float32(np.deg2rad(config.elevation_max_deg))
        scale = np.float32(config.n_rows / (el_hi - np.deg2rad(config.elevation_min_deg)))
        row_f = (el_hi - np.arctan2(z, np.sqrt(horiz2))) * scale
        ok = (row_f >= 0) & (row_f < config.n_rows)
        row = row_f.astype(np.int32)
    ok &= range_m >= config.min_range_m
    pix = row * np.int32(config.n_cols) + col
    pix[~ok] = -1
    return pix


def _nearest(
    pix: np.ndarray, range_m: np.ndarray, point: np.ndarray, n_pix: int, low: int, high: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (and a spare last one), the index (int32, -1 for none) and range (float32, NaN
    for none) of the nearest of the given points.

    One key orders a pixel's returns by range and names the point: the bits of a positive
    float32 sort as the number does, so the key (range bits, index) is least for the nearest,
    and one ``minimum.at`` finds it. Keys are built and read as pairs of 32-bit halves; an empty
    pixel keeps the all-ones key, which reads as index -1 and a NaN range."""
    keys = np.empty(point.size, dtype=np.uint64)
    halves = keys.view(np.uint32).reshape(-1, 2)
    halves[:, low] = point
    halves[:, high] = range_m.view(np.uint32)
    best = np.full(n_pix + 1, np.iinfo(np.uint64).max, dtype=np.uint64)
    np.minimum.at(best, pix, keys)
    out = best.view(np.uint32).reshape(-1, 2)
    return out[:, low].view(np.int32), out[:, high].view(np.float32)


def to_egosphere_reference(
    scan: LadarScan,
    config: EgosphereConfig | None = None,
    T_body_sensor: np.ndarray | None = None,
) -> EgosphereImage:
    """The numpy form of :func:`to_egosphere` (same arguments and result): each point's pixel
    by :func:`_pixel_of`, then one ``minimum.at`` per layer of returns (:func:`_nearest`)."""
    cfg = config or EgosphereConfig()
    check_scan(scan)
    pts = np.asarray(scan.points_xyz, dtype=np.float32)
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    horiz2 = x * x + y * y
    point_range_m = np.sqrt(horiz2 + z * z)
    pix = _pixel_of(scan, cfg, x, y, z, horiz2, point_range_m)
    n_pix, K = cfg.n_rows * cfg.n_cols, cfg.max_returns
    ok = pix >= 0
    n_ok = int(np.count_nonzero(ok))
    n_dropped = int(pix.size - n_ok)
    index = np.full((K, n_pix), -1, dtype=np.int32)
    range_m = np.full((K, n_pix), np.nan, dtype=np.float32)
    low, high = (0, 1) if sys.byteorder == "little" else (1, 0)
    # Layer 0 takes every point: dropped ones go to a spare pixel past the image's end.
    pix[~ok] = n_pix
    points = np.arange(pix.size, dtype=np.uint32)
    taken = ~ok  # points placed in a layer so far, or dropped
    for k in range(K):
        if k:
            rest = np.flatnonzero(~taken)
            if rest.size == 0:
                break
            i, r = _nearest(
                pix[rest], point_range_m[rest], rest.astype(np.uint32), n_pix, low, high
            )
        else:
            i, r = _nearest(pix, point_range_m, points, n_pix, low, high)
        index[k], range_m[k] = i[:n_pix], r[:n_pix]
        if k < K - 1:
            placed = index[k]
            taken[placed[placed >= 0]] = True
    n_overflow = n_ok - int(np.count_nonzero(index >= 0))
    index = np.moveaxis(index.reshape(K, cfg.n_rows, cfg.n_cols), 0, -1)
    range_m = np.moveaxis(range_m.reshape(K, cfg.n_rows, cfg.n_cols), 0, -1)
    T = np.eye(4) if T_body_sensor is None else check_pose(T_body_sensor, "T_body_sensor")
    return EgosphereImage(scan, cfg, index, range_m, T, n_dropped, n_overflow)
