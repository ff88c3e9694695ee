"""Numpy oracle of the compiled fill of :mod:`sp.windowing` (tests only).

:func:`window_mask_reference` is the oracle of :func:`sp.windowing.window_mask`: every window's
(window, row) pairs within its elevation half-span plus ``ELEVATION_MARGIN_RAD``, their column
intervals (wrapping in azimuth) summed into a difference image. The kernel must give the same
mask.
"""

from __future__ import annotations

import numpy as np

from sp.windowing import ELEVATION_MARGIN_RAD, WindowConfig, WindowingError


def window_mask_reference(
    shape: tuple[int, int],
    centers_sensor: np.ndarray,
    sigma_m: np.ndarray,
    row_elevation_rad: np.ndarray,
    config: WindowConfig | None = None,
) -> np.ndarray:
    """:func:`window_mask` in plain numpy, the (window, row) pairs scattered into a difference
    image (the reference the compiled fill is tested against; same arguments and mask)."""
    cfg = config or WindowConfig()
    H, W = shape
    c = np.asarray(centers_sensor, dtype=np.float64).reshape(-1, 3)
    s = np.asarray(sigma_m, dtype=np.float64).reshape(-1)
    if s.shape[0] != c.shape[0]:
        raise WindowingError(f"{c.shape[0]} window centres but {s.shape[0]} sigmas")
    mask = np.zeros((H, W), dtype=bool)
    rows_ok = np.isfinite(row_elevation_rad)
    if c.shape[0] == 0 or not rows_ok.any():
        return mask
    range_m = np.maximum(np.linalg.norm(c, axis=1), 1.0)
    half_m = np.minimum(cfg.base_m + cfg.k_sigma * s, cfg.max_half_m)
    half_ang = np.arctan2(half_m, range_m)
    az = np.arctan2(c[:, 1], c[:, 0])
    el = np.arctan2(c[:, 2], np.hypot(c[:, 0], c[:, 1]))
    col_step = 2 * np.pi / W
    col = ((np.pi - az) / col_step).astype(np.int64)
    half_c = np.ceil(half_ang / col_step).astype(np.int64)
    row_el = np.where(rows_ok, row_elevation_rad, np.inf)
    # (window, row) pairs inside each window's elevation span, then every row's column
    # intervals (wrapping in azimuth) summed into a difference image: one pass, no loop
    k, rows = np.nonzero(
        np.abs(row_el[None, :] - el[:, None]) <= half_ang[:, None] + ELEVATION_MARGIN_RAD
    )
    if k.size == 0:
        return mask
    length = np.minimum(2 * half_c[k] + 1, W)
    start = (col[k] - half_c[k]) % W
    end = start + length
    diff = np.zeros((H, W + 1), dtype=np.int32)
    np.add.at(diff, (rows, start), 1)
    np.add.at(diff, (rows, np.minimum(end, W)), -1)
    wrap = end > W
    np.add.at(diff, (rows[wrap], 0), 1)
    np.add.at(diff, (rows[wrap], end[wrap] - W), -1)
    return np.cumsum(diff[:, :W], axis=1) > 0
