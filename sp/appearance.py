"""Appearance of objects in the camera image: the camera's share of the SP computation function.

Reference 001, 4.5.1 (computation: attributes such as "colour" integrated over the group),
4.4.6 (a camera image is a patch of its sensor egosphere; LADAR points give its pixels range).
Each object's LADAR returns are projected into the camera image taken closest in time; the
mean grey value of the pixels they land on (0..1) is the object's observed camera intensity,
the share of its returns the camera sees is its camera coverage, and, in a colour image, the
excess green of the light from those pixels, ``(2G - R - B) / (R + G + B)`` summed over them
(Woebbecke et al., 1995, the vegetation index of colour cameras), is its excess green: about
0 for grey, brown and white surfaces, 0.3-0.5 for leaves. A ratio of the channels, it does not
change with exposure, gain or the shading of the surface, where the grey value does. Where
the frame carries a depth image, a return whose depth disagrees with the pixel's by more than
``max_depth_gap_m`` is hidden behind something nearer and is not counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import EngineError
from core.geometry import check_pose, se3_inverse
from logs.types import CameraFrame
from sp.camera import PinholeCamera


class AppearanceError(EngineError, ValueError):
    """Points, ids or camera pose of the wrong shape; names them."""


@dataclass(frozen=True)
class AppearanceConfig:
    max_depth_gap_m: float = 0.5  # occlusion test against the frame's depth image
    min_pixels: int = 3  # fewer projected returns: no appearance for that object


@dataclass
class Appearance:
    """Per object: ids (A,) int64, intensity (A,) float64 mean grey 0..1, coverage (A,)
    float64 share of the object's returns seen by the camera, n (A,) int64 returns seen,
    excess_green (A,) float64 in [-1, 2] (NaN in a grey image or on black pixels)."""

    ids: np.ndarray
    intensity: np.ndarray
    coverage: np.ndarray
    n: np.ndarray
    excess_green: np.ndarray


def object_appearance(
    points_world: np.ndarray,
    ids: np.ndarray,
    camera: CameraFrame,
    T_world_camera: np.ndarray,
    config: AppearanceConfig | None = None,
) -> Appearance:
    """Appearance of every object of ``ids`` ((N,) int64, >= 0) from its returns
    ``points_world`` ((N, 3) world metres) in ``camera`` (optical frame pose
    ``T_world_camera``)."""
    cfg = config or AppearanceConfig()
    p = np.asarray(points_world, dtype=np.float64)
    ids = np.asarray(ids, dtype=np.int64)
    if p.ndim != 2 or p.shape[1] != 3 or ids.shape != (p.shape[0],):
        raise AppearanceError(f"points {p.shape} and ids {ids.shape} do not pair up")
    T_cam_world = se3_inverse(check_pose(T_world_camera, "T_world_camera"))
    model = PinholeCamera.from_frame(camera)
    p_cam = p @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    uv, on = model.project(p_cam)
    col = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, model.width - 1)
    row = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, model.height - 1)
    if camera.depth is not None:
        d = camera.depth[row, col].astype(np.float64)
        on &= np.isfinite(d) & (np.abs(d - p_cam[:, 2]) <= cfg.max_depth_gap_m)
    # the few objects' indices by a search in their sorted ids, and the grey value only at
    # the pixels the seen returns land on: the whole image's grey is mostly never read
    uniq = np.unique(ids)
    inv = np.searchsorted(uniq, ids)
    total = np.bincount(inv, minlength=uniq.size)
    px = camera.image[row[on], col[on]].astype(np.float64)
    grey = px.mean(axis=1) if px.ndim == 2 else px
    seen = np.bincount(inv[on], minlength=uniq.size)
    sums = np.bincount(inv[on], weights=grey / 255.0, minlength=uniq.size)
    excess_green = np.full(uniq.size, np.nan)
    if px.ndim == 2:
        light = sums * (3.0 * 255.0)  # R + G + B summed: the grey values' sum, rescaled
        g = np.bincount(inv[on], weights=px[:, 1], minlength=uniq.size)
        lit = light > 0
        excess_green[lit] = 3.0 * g[lit] / light[lit] - 1.0  # (2G - R - B) / (R + G + B)
    keep = seen >= cfg.min_pixels
    return Appearance(
        ids=uniq[keep],
        intensity=sums[keep] / seen[keep],
        coverage=seen[keep] / total[keep],
        n=seen[keep].astype(np.int64),
        excess_green=excess_green[keep],
    )
