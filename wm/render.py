"""Pictures of a run: every map level (elevation with SP entity labels, cost) with the KD's
entities drawn on top (maps.pictures does the layers; this adds the entities).

Two sources: a live node (:func:`render_run`, at the end of ``wm run``) or a KD file alone
(:func:`render_maps` over :func:`wm.tiles.stored_maps`: the map the run stored as tiles, around
the last self pose; reference 001, 4.4.11, long-term memory holds the maps). Images are BGR
uint8 PNGs, north up; an entity is a circle at its world position, green when confirmed,
yellow when hypothesized.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

import kd_store
from kd_store import Status
from maps.level import MapLevel
from maps.pictures import render_layer, save_png
from maps.stack import MapStack

CONFIRMED_BGR = (0, 220, 0)
HYPOTHESIZED_BGR = (0, 220, 220)
PANEL_PX = 512
LAYERS = (("elevation", "entity_id"), ("cost", None))  # (layer, overlay) per picture


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


def object_positions(
    kd: kd_store.KnowledgeDatabase, self_id: int | None
) -> tuple[np.ndarray, list[bool]]:
    """World xy (N, 2) metres of the KD's object- and group-level entities (confirmed or
    hypothesized, at their last state, not the vehicle) and whether each is confirmed."""
    frames = [
        f
        for f in kd.entities()
        if f.id != self_id and f.state is not None and f.state.frame == "world"
        and f.status in (Status.CONFIRMED, Status.HYPOTHESIZED) and f.level >= 4
        and f.name != "self"
    ]  # fmt: skip
    xy = np.array([f.state.position_xyz[:2] for f in frames]).reshape(-1, 2)
    return xy, [f.status == Status.CONFIRMED for f in frames]


def render_maps(
    kd: kd_store.KnowledgeDatabase,
    stack: MapStack,
    self_id: int | None,
    out_dir: Path,
    levels: list[str] | None = None,
) -> list[Path]:
    """One PNG per level and layer (elevation, cost) of ``stack`` (the ``levels`` named, default
    all) into ``out_dir``, the KD's entities on top; returns the paths."""
    xy, confirmed = object_positions(kd, self_id)
    paths = []
    for i, lvl in enumerate(stack.levels):
        if levels is not None and lvl.name not in levels:
            continue
        scale = max(1, PANEL_PX // lvl.size)
        for layer, overlay in LAYERS:
            img = render_layer(
                lvl, layer, scale=scale, T_world_body=stack.T_world_body, overlay=overlay
            )
            draw_entities(img, lvl, scale, xy, confirmed)
            paths.append(save_png(img, out_dir / f"level{i + 2}_{lvl.name}_{layer}.png"))
    return paths


def render_run(node, out_dir: Path) -> list[Path]:
    """Pictures of a live node's maps and KD (see :func:`render_maps`)."""
    return render_maps(node.kd, node.stack, node.self_id, out_dir)
