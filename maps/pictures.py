"""Pictures of map layers: colour maps, hill shading, labels, the vehicle, a scale bar, a legend.

Images are (H, W, 3) uint8 in OpenCV's BGR order, north up (window row 0, the southern edge,
is the bottom image row), one window cell drawn as ``scale`` x ``scale`` pixels. Cells with no
value are drawn in :data:`NO_DATA_BGR`. OpenCV draws and writes the PNG (an adapter at the edge;
the maps core stays numpy).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from core.errors import EngineError
from maps.level import MapLevel

NO_DATA_BGR = (48, 48, 48)
VEHICLE_BGR = (0, 0, 255)
TEXT_BGR = (255, 255, 255)
LEGEND_PX = 28  # height of the legend strip under each panel
COLOUR_MAPS = {"elevation": cv2.COLORMAP_TURBO, "occupancy": cv2.COLORMAP_JET}
LABEL_LAYERS = ("entity_id", "class_id")


class PictureError(EngineError, ValueError):
    """A picture request that cannot be drawn (names the value)."""


def hillshade(elevation: np.ndarray, resolution_m: float, azimuth_deg: float = 315.0,
              altitude_deg: float = 45.0) -> np.ndarray:  # fmt: skip
    """Lambertian shading (H, W) in [0, 1] of a height grid (window order, rows along +y),
    lit from ``azimuth_deg`` (clockwise from north) at ``altitude_deg``; NaN -> 1."""
    e = np.asarray(elevation, dtype=np.float64)
    filled = np.where(np.isfinite(e), e, np.nanmean(e) if np.isfinite(e).any() else 0.0)
    gy, gx = np.gradient(filled, resolution_m)
    az, alt = np.radians(azimuth_deg), np.radians(altitude_deg)
    light = np.array([np.sin(az) * np.cos(alt), np.cos(az) * np.cos(alt), np.sin(alt)])
    normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    shade = np.clip(normal @ light, 0.0, 1.0)
    return np.where(np.isfinite(e), shade, 1.0)


def colourise(values: np.ndarray, vmin: float, vmax: float, colour_map: int) -> np.ndarray:
    """Values (H, W) -> BGR (H, W, 3) uint8 through an OpenCV colour map; NaN -> no data."""
    v = np.asarray(values, dtype=np.float64)
    span = vmax - vmin if vmax > vmin else 1.0
    idx = np.clip((np.nan_to_num(v, nan=vmin) - vmin) / span * 255.0, 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(idx, colour_map)
    img[~np.isfinite(v)] = NO_DATA_BGR
    return img


def label_colours(ids: np.ndarray) -> np.ndarray:
    """A stable, distinct-looking BGR colour (…, 3) uint8 per integer id (hash of the id)."""
    h = (np.asarray(ids, dtype=np.int64).astype(np.uint64) * np.uint64(2654435761)) % np.uint64(
        2**24
    )
    bgr = np.stack([(h >> np.uint64(s)) & np.uint64(255) for s in (0, 8, 16)], axis=-1)
    return (bgr.astype(np.uint16) // 2 + 96).astype(np.uint8)


def render_layer(
    level: MapLevel,
    layer: str = "elevation",
    *,
    scale: int = 2,
    T_world_body: np.ndarray | None = None,
    overlay: str | None = None,
    value_range: tuple[float, float] | None = None,
) -> np.ndarray:
    """Picture of one layer of ``level`` (BGR uint8), with legend, scale bar and vehicle.

    ``overlay`` ("entity_id" or "class_id") blends label colours over labelled cells. Label
    layers themselves are drawn with one colour per id. ``value_range`` fixes the colour
    scale (default: the finite min..max). Elevation is hill shaded.
    """
    if not (isinstance(scale, int) and scale >= 1):
        raise PictureError(f"scale must be an int >= 1 pixels per cell, got {scale!r}")
    values = level.window(layer)
    finite = np.isfinite(values) if values.dtype.kind == "f" else values >= 0
    if layer in LABEL_LAYERS:
        img = np.where(finite[..., None], label_colours(values), np.uint8(NO_DATA_BGR))
        img = img.astype(np.uint8)
        lo, hi = 0.0, 0.0
    else:
        v = values.astype(np.float64)
        v[~finite] = np.nan
        lo, hi = value_range or _finite_range(v)
        img = colourise(v, lo, hi, COLOUR_MAPS.get(layer, cv2.COLORMAP_VIRIDIS))
        if layer == "elevation":
            shade = 0.35 + 0.65 * hillshade(v, level.resolution_m)
            img = np.where(finite[..., None], img * shade[..., None], img).astype(np.uint8)
    if overlay is not None:
        ids = level.window(overlay)
        lab = ids >= 0
        blend = 0.5 * img + 0.5 * label_colours(ids)
        img = np.where(lab[..., None], blend, img).astype(np.uint8)
    img = np.ascontiguousarray(img[::-1])  # north up
    img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    if T_world_body is not None:
        _draw_vehicle(img, level, scale, np.asarray(T_world_body, dtype=np.float64))
    _draw_scale_bar(img, level.resolution_m / scale)
    return _with_legend(img, f"{level.name} {level.resolution_m:g} m: {layer}", lo, hi, layer)


def render_levels(
    levels: list[MapLevel],
    layer: str = "elevation",
    *,
    panel_px: int = 512,
    T_world_body: np.ndarray | None = None,
    overlay: str | None = None,
) -> np.ndarray:
    """All levels side by side (finest first), each panel about ``panel_px`` wide."""
    if not levels:
        raise PictureError("render_levels needs at least one level")
    panels = [
        render_layer(
            lvl,
            layer,
            scale=max(1, panel_px // lvl.size),
            T_world_body=T_world_body,
            overlay=overlay,
        )
        for lvl in levels
    ]
    h = max(p.shape[0] for p in panels)
    padded = [cv2.copyMakeBorder(p, 0, h - p.shape[0], 0, 4, cv2.BORDER_CONSTANT) for p in panels]
    return np.hstack(padded)


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write a BGR uint8 picture to ``path`` as PNG (folders made as needed)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(image)):
        raise PictureError(f"could not write a PNG to {path}")
    return path


def _finite_range(v: np.ndarray) -> tuple[float, float]:
    ok = np.isfinite(v)
    if not ok.any():
        return 0.0, 1.0
    return float(v[ok].min()), float(v[ok].max())


def _draw_vehicle(img: np.ndarray, level: MapLevel, scale: int, T: np.ndarray) -> None:
    """A red arrow-head at the body position, pointing along the body x axis."""
    lo, _ = level.bounds_xy
    m_per_px = level.resolution_m / scale
    h = img.shape[0]

    def px(xy: np.ndarray) -> tuple[int, int]:
        u = (xy[0] - lo[0]) / m_per_px
        v = h - (xy[1] - lo[1]) / m_per_px
        return round(u), round(v)

    p, fwd = T[:2, 3], T[:2, 0] / max(np.linalg.norm(T[:2, 0]), 1e-9)
    left = np.array([-fwd[1], fwd[0]])
    size_m = 6.0 * m_per_px
    tri = [p + fwd * size_m, p - fwd * size_m * 0.6 + left * size_m * 0.6,
           p - fwd * size_m * 0.6 - left * size_m * 0.6]  # fmt: skip
    cv2.fillPoly(img, [np.array([px(q) for q in tri], dtype=np.int32)], VEHICLE_BGR)


def _draw_scale_bar(img: np.ndarray, m_per_px: float) -> None:
    """A white bar of a round length (1, 2 or 5 x 10^k m) about a fifth of the width."""
    target_m = img.shape[1] * m_per_px / 5.0
    k = np.floor(np.log10(target_m))
    length_m = max(m for m in (1.0, 2.0, 5.0) if m * 10**k <= target_m) * 10**k
    n = max(1, round(length_m / m_per_px))
    y = img.shape[0] - 8
    cv2.rectangle(img, (8, y - 3), (8 + n - 1, y), TEXT_BGR, thickness=-1)  # corners inclusive
    cv2.putText(img, f"{length_m:g} m", (8, y - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4, TEXT_BGR, 1)


def _with_legend(img: np.ndarray, title: str, lo: float, hi: float, layer: str) -> np.ndarray:
    """Append a legend strip: title, and a colour bar from ``lo`` to ``hi``."""
    strip = np.zeros((LEGEND_PX, img.shape[1], 3), dtype=np.uint8)
    cv2.putText(strip, title, (4, 11), cv2.FONT_HERSHEY_SIMPLEX, 0.35, TEXT_BGR, 1)
    if layer not in LABEL_LAYERS:
        w = max(16, img.shape[1] // 3)
        bar = np.linspace(0, 255, w).astype(np.uint8)[None].repeat(8, axis=0)
        colour = cv2.applyColorMap(bar, COLOUR_MAPS.get(layer, cv2.COLORMAP_VIRIDIS))
        x0 = 4
        strip[16:24, x0 : x0 + w] = colour[:, : min(w, img.shape[1] - x0)]
        text = f"{lo:.3g} .. {hi:.3g}"
        cv2.putText(strip, text, (x0 + w + 4, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.35, TEXT_BGR, 1)
    return np.vstack([img, strip])
