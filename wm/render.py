"""Pictures of a run: every map level (elevation with SP entity labels, cost) with the KD's
entities drawn on top (maps.pictures does the layers; this adds the entities).

Images are BGR uint8 PNGs, north up; an entity is a circle at its world position, green when
confirmed, yellow when hypothesized.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from kd_store import Status
from maps.level import MapLevel
from maps.pictures import render_layer, save_png

CONFIRMED_BGR = (0, 220, 0)
HYPOTHESIZED_BGR = (0, 220, 220)
PANEL_PX = 512


def draw_entities(img: np.ndarray, level: MapLevel, scale: int, xy: np.ndarray, confirmed) -> None:
    """Circles at world points ``xy`` (N, 2) on a picture of ``level`` drawn at ``scale``."""
    lo, _ = level.bounds_xy
    m_per_px = level.resolution_m / scale
    h = level.size * scale
    for (x, y), ok in zip(xy, confirmed, strict=True):
        u, v = round((x - lo[0]) / m_per_px), round(h - (y - lo[1]) / m_per_px)
        if 0 <= u < img.shape[1] and 0 <= v < h:
            colour = CONFIRMED_BGR if ok else HYPOTHESIZED_BGR
            cv2.circle(img, (u, v), 4, colour, 1)


def render_run(node, out_dir: Path) -> list[Path]:
    """One PNG per level and layer (elevation, cost) into ``out_dir``; returns the paths."""
    frames = [
        f
        for f in node.kd.entities()
        if f.id != node.self_id and f.state is not None and f.state.frame == "world"
        and f.status in (Status.CONFIRMED, Status.HYPOTHESIZED) and f.level >= 4
    ]  # fmt: skip
    xy = np.array([f.state.position_xyz[:2] for f in frames]).reshape(-1, 2)
    confirmed = [f.status == Status.CONFIRMED for f in frames]
    paths = []
    for i, lvl in enumerate(node.stack.levels):
        scale = max(1, PANEL_PX // lvl.size)
        for layer, overlay in (("elevation", "entity_id"), ("cost", None)):
            img = render_layer(
                lvl, layer, scale=scale, T_world_body=node.stack.T_world_body, overlay=overlay
            )
            draw_entities(img, lvl, scale, xy, confirmed)
            paths.append(save_png(img, out_dir / f"level{i + 2}_{lvl.name}_{layer}.png"))
    return paths
