"""Stereo disparity and range from disparity (reference 001, 4.5.6 Level 1: "for a pair of stereo
images, disparity can be computed at each pixel ... when combined with camera vergence and
knowledge of camera spacing, disparity can be used to compute range for each pixel").

Rectified pairs only: a left pixel ``(x, y)`` matches the right pixel ``(x - d, y)``. The
matcher is OpenCV's semi-global block matching (an adapter at the edge); the geometry is numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import EngineError


class StereoError(EngineError, ValueError):
    """A stereo pair or camera geometry that cannot give disparity or range; names the value."""


@dataclass(frozen=True)
class StereoConfig:
    """Matcher settings: disparities searched 0..max_disparity_px (rounded up to a multiple
    of 16), block side block_px (odd), uniqueness margin in percent."""

    max_disparity_px: int = 64
    block_px: int = 5
    uniqueness_pct: int = 10

    def __post_init__(self) -> None:
        if self.max_disparity_px < 1 or self.block_px < 1 or self.block_px % 2 == 0:
            raise StereoError(
                f"need max_disparity_px >= 1 and an odd block_px, got {self.max_disparity_px}, "
                f"{self.block_px}"
            )


def _gray8(image: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 3:
        a = a.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    if a.ndim != 2 or a.dtype.kind not in "fiu":
        raise StereoError(f"{name} must be an (H, W) or (H, W, 3) image, got {a.shape} {a.dtype}")
    if a.dtype != np.uint8:
        lo, hi = float(np.nanmin(a)), float(np.nanmax(a))
        a = np.clip((a - lo) * (255.0 / max(hi - lo, 1e-9)), 0, 255).astype(np.uint8)
    return a


def stereo_disparity(
    left: np.ndarray, right: np.ndarray, config: StereoConfig | None = None
) -> np.ndarray:
    """Disparity (H, W) float32 pixels of a rectified pair at the left image's pixels, NaN
    where no reliable match was found."""
    import cv2

    cfg = config or StereoConfig()
    L, R = _gray8(left, "left image"), _gray8(right, "right image")
    if L.shape != R.shape:
        raise StereoError(f"stereo images differ in shape: left {L.shape}, right {R.shape}")
    n_disp = 16 * int(np.ceil(cfg.max_disparity_px / 16))
    if n_disp >= L.shape[1]:
        raise StereoError(f"max_disparity_px {cfg.max_disparity_px} exceeds the width {L.shape[1]}")
    b = cfg.block_px
    sgbm = cv2.StereoSGBM_create(
        minDisparity=0,
        numDisparities=n_disp,
        blockSize=b,
        P1=8 * b * b,
        P2=32 * b * b,
        uniquenessRatio=cfg.uniqueness_pct,
        speckleWindowSize=100,
        speckleRange=2,
        disp12MaxDiff=1,
        mode=cv2.STEREO_SGBM_MODE_HH,
    )
    d = sgbm.compute(L, R).astype(np.float32) / 16.0  # fixed point, 4 fractional bits
    d[d < 0] = np.nan
    return d


def disparity_to_depth(disparity_px: np.ndarray, focal_px: float, baseline_m: float) -> np.ndarray:
    """Depth along the optical axis, ``Z = f B / d`` metres (H, W) float32; NaN where the
    disparity is unknown or not positive (a point at infinity has no range)."""
    if not (np.isfinite(focal_px) and focal_px > 0 and np.isfinite(baseline_m) and baseline_m > 0):
        raise StereoError(f"focal_px={focal_px} and baseline_m={baseline_m} must be positive")
    d = np.asarray(disparity_px, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.float32(focal_px * baseline_m) / d
    z[~(d > 0)] = np.nan
    return z
