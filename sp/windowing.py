"""Windowing: attention masks on the egosphere image (the SP windowing function).

Reference 001, 4.5.1 (windowing: "attention ... to regions of the image"), 3 (focus of
attention), 4.5.3 (predicted entities define windows; "the size of the window grows when
confidence is low and narrows when it is high").

A window is a rectangle of pixels around the projection of a world point; its half-size in
metres is ``base_m + k_sigma * sigma_m`` (the entity's position uncertainty, so a poorly known
entity gets a wide window), turned into rows and columns by the range and the image's angular
steps. Pixels the world model did not predict (grouped but unexplained) join the mask for the
next cycle.

:func:`window_mask` computes each window's centre and half-sizes in numpy and fills the rows'
column intervals in one compiled pass (:func:`_fill_windows_kernel`);
``window_mask_reference`` (a test oracle, in ``tests/kernel_reference``) is the numpy
form it is tested against (the same mask).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from core.errors import EngineError

# Margin (rad) added to a window's elevation half-span when choosing the image rows it covers
# (rows are compared by their mean elevation).
ELEVATION_MARGIN_RAD = 0.01


class WindowingError(EngineError, ValueError):
    """Window centres or sizes of the wrong shape; names them."""


@dataclass(frozen=True)
class WindowConfig:
    base_m: float = 1.0
    k_sigma: float = 3.0
    max_half_m: float = 15.0


def window_mask(
    shape: tuple[int, int],
    centers_sensor: np.ndarray,
    sigma_m: np.ndarray,
    row_elevation_rad: np.ndarray,
    config: WindowConfig | None = None,
) -> np.ndarray:
    """(H, W) bool mask of the windows around points ``centers_sensor`` (A, 3) (sensor frame,
    m) with position uncertainty ``sigma_m`` (A,) m. ``row_elevation_rad`` (H,): elevation of
    each row (NaN for rows with no returns). Columns follow :mod:`sp.egosphere`'s azimuth bins.
    The same mask as ``window_mask_reference``.
    """
    cfg = config or WindowConfig()
    H, W = shape
    c = np.asarray(centers_sensor, dtype=np.float64).reshape(-1, 3)
    s = np.asarray(sigma_m, dtype=np.float64).reshape(-1)
    if s.shape[0] != c.shape[0]:
        raise WindowingError(f"{c.shape[0]} window centres but {s.shape[0]} sigmas")
    rows_ok = np.isfinite(row_elevation_rad)
    if c.shape[0] == 0 or not rows_ok.any():
        return np.zeros((H, W), dtype=bool)
    # per window (A values) in numpy, as the reference: its arctan2 is not libm's bit for bit
    range_m = np.maximum(np.linalg.norm(c, axis=1), 1.0)
    half_m = np.minimum(cfg.base_m + cfg.k_sigma * s, cfg.max_half_m)
    half_ang = np.arctan2(half_m, range_m)
    az = np.arctan2(c[:, 1], c[:, 0])
    el = np.arctan2(c[:, 2], np.hypot(c[:, 0], c[:, 1]))
    col_step = 2 * np.pi / W
    col = ((np.pi - az) / col_step).astype(np.int64)
    half_c = np.ceil(half_ang / col_step).astype(np.int64)
    row_el = np.where(rows_ok, row_elevation_rad, np.inf).astype(np.float64)
    return _fill_windows_kernel(H, W, row_el, el, half_ang + ELEVATION_MARGIN_RAD, col, half_c)


@numba.njit(cache=True, nogil=True)
def _fill_windows_kernel(H, W, row_el, el, reach, col, half_c):  # pragma: no cover
    """The rows' union of window column intervals, row by row.

    row_el: (H,) float64 rad (inf for rows without returns); el, reach: (A,) float64 rad, each
    window's elevation and elevation half-span (plus ``ELEVATION_MARGIN_RAD``); col, half_c: (A,)
    int64, its centre column and column half-width. A window covers row ``i`` where
    ``|row_el[i] - el| <= reach``, there columns ``col - half_c`` to ``col + half_c`` (at most
    W, wrapping in azimuth). Returns (H, W) bool.

    Each row's intervals go into a difference row, whose running sum is positive exactly on
    their union (the reference's cumsum > 0, with no (H, W + 1) image or scatter).
    """
    mask = np.zeros((H, W), dtype=np.bool_)
    diff = np.empty(W + 1, dtype=np.int64)
    for i in range(H):
        touched = False
        for a in range(el.shape[0]):
            if not abs(row_el[i] - el[a]) <= reach[a]:
                continue
            if not touched:
                diff[:] = 0
                touched = True
            length = min(2 * half_c[a] + 1, W)
            start = (col[a] - half_c[a]) % W
            end = start + length
            diff[start] += 1
            diff[min(end, W)] -= 1
            if end > W:
                diff[0] += 1
                diff[end - W] -= 1
        if touched:
            run = 0
            for j in range(W):
                run += diff[j]
                mask[i, j] = run > 0
    return mask
