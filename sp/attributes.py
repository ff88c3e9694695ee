"""Level 1 attribute images (reference 001, 4.5.6 "Level 1 Measurement and Computation").

Per pixel: intensity (or colour), spatial intensity gradients ``dI/dx, dI/dy``, the temporal
gradient ``dI/dt``, range, spatial range gradients ``dr/dx, dr/dy``, surface normals,
roughness / texture ``tx`` and range rate ``dr/dt``; every attribute image stays in registration
with the image it came from (4.4.4: "maintained in registration with the other attribute
images"). Conventions: images are (H, W) float32 ``[row, col]``; ``x`` is the column (right) and
``y`` the row (down); gradients are per pixel; NaN marks unknown (no return, off the image) and
propagates. Numpy core, ``cv2.boxFilter`` for local sums.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import EngineError
from sp.egosphere import EgosphereImage


class AttributeImageError(EngineError, ValueError):
    """An image of the wrong shape or dtype, or an impossible time step; names the value."""


def intensity(image: np.ndarray, name: str = "image") -> np.ndarray:
    """(H, W) grey or (H, W, 3) RGB numeric image -> (H, W) float32 intensity, same units
    (RGB weighted 0.299, 0.587, 0.114)."""
    a = np.asarray(image)
    if a.dtype.kind not in "fiu":
        raise AttributeImageError(f"{name} has dtype {a.dtype}; expected a numeric image")
    if a.ndim == 2:
        return a.astype(np.float32, copy=False)
    if a.ndim == 3 and a.shape[2] == 3:
        w = np.array([0.299, 0.587, 0.114], dtype=np.float32)
        return (a.astype(np.float32) @ w).astype(np.float32)
    raise AttributeImageError(f"{name} has shape {a.shape}; expected (H, W) or (H, W, 3)")


def _check_pair(now: np.ndarray, before: np.ndarray, dt_s: float, what: str) -> None:
    if np.shape(now) != np.shape(before):
        raise AttributeImageError(
            f"{what}: images differ in shape, {np.shape(now)} now vs {np.shape(before)} before"
        )
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise AttributeImageError(f"{what}: time step dt_s={dt_s} must be positive")


def spatial_gradients(image: np.ndarray, wrap_x: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference gradients ``(d/dx, d/dy)`` per pixel of an (H, W) attribute image.

    Edge pixels use one-sided differences; ``wrap_x`` treats columns as a closed circle (a full
    360 degree egosphere). NaN where a needed neighbour is NaN."""
    a = intensity(image)
    if min(a.shape) < 2:
        raise AttributeImageError(f"image of shape {a.shape} is too small for gradients")
    if wrap_x:
        gx = 0.5 * (np.roll(a, -1, axis=1) - np.roll(a, 1, axis=1))
    else:
        gx = np.gradient(a, axis=1)
    gy = np.gradient(a, axis=0)
    return gx.astype(np.float32), gy.astype(np.float32)


def temporal_gradient(now: np.ndarray, before: np.ndarray, dt_s: float) -> np.ndarray:
    """``dI/dt``: (now - before) / dt_s, per second (4.5.6: "subtracting the intensity of a
    pixel at time t-1 from the intensity at time t")."""
    _check_pair(now, before, dt_s, "temporal gradient")
    return ((intensity(now) - intensity(before)) / np.float32(dt_s)).astype(np.float32)


def range_rate(range_now_m: np.ndarray, range_before_m: np.ndarray, dt_s: float) -> np.ndarray:
    """``dr/dt`` in m/s per pixel: "temporal differences in range at a point" (4.5.6)."""
    _check_pair(range_now_m, range_before_m, dt_s, "range rate")
    return ((range_now_m - range_before_m) / np.float32(dt_s)).astype(np.float32)


def surface_normals(xyz: np.ndarray, wrap_x: bool = False) -> np.ndarray:
    """Unit surface normals (H, W, 3) float32 from an (H, W, 3) image of points.

    The normal is the cross product of the central differences along rows and columns,
    turned to face the sensor (``n . p < 0``); NaN where a neighbour is missing."""
    p = np.asarray(xyz, dtype=np.float32)
    if p.ndim != 3 or p.shape[2] != 3 or min(p.shape[:2]) < 3:
        raise AttributeImageError(f"xyz image must be (H>=3, W>=3, 3), got shape {p.shape}")
    if wrap_x:
        dx = np.roll(p, -1, axis=1) - np.roll(p, 1, axis=1)
    else:
        dx = np.full_like(p, np.nan)
        dx[:, 1:-1] = p[:, 2:] - p[:, :-2]
    dy = np.full_like(p, np.nan)
    dy[1:-1] = p[2:] - p[:-2]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.where(norm > 0, n / norm, np.nan)
    flip = np.einsum("ijk,ijk->ij", n, p) > 0
    n[flip] *= -1
    return n.astype(np.float32)


def roughness(
    xyz: np.ndarray, normals: np.ndarray | None = None, window: int = 3, wrap_x: bool = False
) -> np.ndarray:
    """Texture ``tx`` (4.5.6: "differences in range at adjacent pixels can be used to compute
    ... surface roughness, or texture"), metres, from an (H, W, 3) image of points.

    At each pixel the second differences of the points along the row and the column are
    projected on the surface normal; ``tx`` is their RMS over a ``window`` x ``window``
    neighbourhood. Any plane gives 0 (a second difference of points on a plane lies in the
    plane), whatever its slope or distance; bumps and vegetation give their height scale.
    NaN where the pixel or its whole neighbourhood is unknown."""
    import cv2

    p = np.asarray(xyz, dtype=np.float32)
    if p.ndim != 3 or p.shape[2] != 3 or min(p.shape[:2]) < 3 or window < 1 or window % 2 == 0:
        raise AttributeImageError(
            f"roughness needs an (H>=3, W>=3, 3) point image and an odd window; got shape "
            f"{p.shape}, window {window}"
        )
    n = surface_normals(p, wrap_x) if normals is None else np.asarray(normals, np.float32)
    if wrap_x:
        d2x = np.roll(p, 1, axis=1) - 2 * p + np.roll(p, -1, axis=1)
    else:
        d2x = np.full_like(p, np.nan)
        d2x[:, 1:-1] = p[:, :-2] - 2 * p[:, 1:-1] + p[:, 2:]
    d2y = np.full_like(p, np.nan)
    d2y[1:-1] = p[:-2] - 2 * p[1:-1] + p[2:]
    opts = {"normalize": False, "borderType": cv2.BORDER_CONSTANT}
    total = np.zeros(p.shape[:2], np.float32)
    count = np.zeros(p.shape[:2], np.float32)
    for d2 in (d2x, d2y):
        h = np.einsum("ijk,ijk->ij", d2, n)
        ok = np.isfinite(h)
        total += cv2.boxFilter(
            np.where(ok, h * h, 0.0).astype(np.float32), -1, (window,) * 2, **opts
        )
        count += cv2.boxFilter(ok.astype(np.float32), -1, (window, window), **opts)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.sqrt(total / count).astype(np.float32)
    out[(count == 0) | ~np.all(np.isfinite(p), axis=2)] = np.nan
    return out


@dataclass
class Level1Attributes:
    """Registered level-1 attribute images of one sensor frame; any may be None when the
    sensor gives no such signal. (H, W) float32 unless stated; ``normals`` is (H, W, 3)."""

    t_ns: int
    intensity: np.ndarray | None = None
    dI_dx: np.ndarray | None = None
    dI_dy: np.ndarray | None = None
    dI_dt: np.ndarray | None = None
    range_m: np.ndarray | None = None
    dr_dx: np.ndarray | None = None
    dr_dy: np.ndarray | None = None
    dr_dt: np.ndarray | None = None
    normals: np.ndarray | None = None
    roughness_m: np.ndarray | None = None

    def names(self) -> list[str]:
        """The attribute images present."""
        return [k for k, v in vars(self).items() if k != "t_ns" and v is not None]


def image_attributes(
    t_ns: int, image: np.ndarray, previous: Level1Attributes | None = None
) -> Level1Attributes:
    """Attributes of a camera image: intensity, its spatial gradients and, given the previous
    frame's attributes, the temporal gradient."""
    I = intensity(image)
    gx, gy = spatial_gradients(I)
    out = Level1Attributes(t_ns=int(t_ns), intensity=I, dI_dx=gx, dI_dy=gy)
    if previous is not None and previous.intensity is not None:
        out.dI_dt = temporal_gradient(I, previous.intensity, (t_ns - previous.t_ns) * 1e-9)
    return out


def egosphere_attributes(
    image: EgosphereImage, previous: Level1Attributes | None = None
) -> Level1Attributes:
    """Attributes of a LADAR egosphere image (nearest return per pixel): range, its gradients,
    surface normals, roughness, intensity and its gradients, and with the previous frame the
    range rate and temporal intensity gradient. Columns wrap (a full turn of azimuth)."""
    r = image.range_first
    I = image.intensity[..., 0]
    gx, gy = spatial_gradients(I, wrap_x=True)
    rx, ry = spatial_gradients(r, wrap_x=True)
    out = Level1Attributes(
        t_ns=image.t_ns,
        intensity=I,
        dI_dx=gx,
        dI_dy=gy,
        range_m=r,
        dr_dx=rx,
        dr_dy=ry,
    )
    xyz = image.xyz[..., 0, :]
    out.normals = surface_normals(xyz, wrap_x=True)
    out.roughness_m = roughness(xyz, out.normals, wrap_x=True)
    if previous is not None and previous.range_m is not None:
        dt = (image.t_ns - previous.t_ns) * 1e-9
        out.dr_dt = range_rate(r, previous.range_m, dt)
        out.dI_dt = temporal_gradient(I, previous.intensity, dt)
    return out


def attribute_pyramids(
    attributes: Level1Attributes, levels: int = 4
) -> dict[str, list[np.ndarray]]:
    """Pyramids of scale (4.5.5) of every attribute image present: level 0 as computed, each
    next level half the size by averaging 2x2 blocks of known (finite) pixels, NaN where a block
    holds none. A 256x256 image gives 256, 128, 64 and 32; normals (H, W, 3) are averaged per
    component and scaled back to unit length."""
    from maps.pyramid import build_pyramid

    out: dict[str, list[np.ndarray]] = {}
    for name in attributes.names():
        a = getattr(attributes, name)
        if a.ndim == 2:
            out[name] = build_pyramid(a, levels, valid=np.isfinite(a))
            continue
        comps = [build_pyramid(a[..., i], levels, valid=np.isfinite(a[..., i])) for i in range(3)]
        stacked = [np.stack(level, axis=-1) for level in zip(*comps, strict=True)]
        with np.errstate(invalid="ignore", divide="ignore"):
            out[name] = [v / np.linalg.norm(v, axis=-1, keepdims=True) for v in stacked]
    return out
