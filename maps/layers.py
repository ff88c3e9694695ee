"""Named map layers: what each layer holds, its dtype, unit and the value of an empty cell.

Every level of the map stack holds the same set of layers, each a 2-D array of the level's
shape (reference 001, 4.4.7: "Maps typically have a number of overlays that are registered
with the map"; map pixel attributes include elevation, roughness, slope, traversability and
pointers to entities). A layer's ``fill`` is what a cell holds before anything is known about
it and after it leaves the window.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.errors import EngineError


class LayerError(EngineError, ValueError):
    """An unknown layer name or a layer specification that cannot be built."""


@dataclass(frozen=True, slots=True)
class LayerSpec:
    """One named layer: ``dtype`` of its cells, the ``fill`` of an empty cell, its ``unit``."""

    name: str
    dtype: str
    fill: float | int
    unit: str = ""
    doc: str = ""

    def empty(self, shape: tuple[int, int]) -> np.ndarray:
        """A new array of ``shape`` filled with this layer's empty value."""
        return np.full(shape, self.fill, dtype=np.dtype(self.dtype))


NAN = math.nan  # one NaN object (wm.config reads NaN as it): equal specs compare equal

# The default layers of every level. Heights are world z in metres; times int64 nanoseconds.
DEFAULT_LAYERS: tuple[LayerSpec, ...] = (
    LayerSpec("elevation", "float32", NAN, "m", "ground height estimate (Kalman mean), world z"),
    LayerSpec("elevation_var", "float32", NAN, "m^2", "variance of the ground height estimate"),
    LayerSpec("elevation_min", "float32", NAN, "m", "lowest point seen in the cell"),
    LayerSpec("elevation_max", "float32", NAN, "m", "highest point seen in the cell"),
    LayerSpec("count", "int32", 0, "points", "ground points fused into the elevation"),
    LayerSpec("obstacle_count", "int32", 0, "points", "points above the ground estimate"),
    LayerSpec("z_weight", "float64", 0.0, "1/m^2", "sum of ground point weights 1/variance"),
    LayerSpec("z_mean", "float64", NAN, "m", "weighted mean height of ground points"),
    LayerSpec("z_sq_dev_sum", "float64", 0.0, "m^2/m^2", "weighted sum of squared deviations"),
    LayerSpec("roughness", "float32", NAN, "m", "weighted std of ground heights in the cell"),
    LayerSpec("slope", "float32", NAN, "rad", "ground slope from neighbouring elevations"),
    LayerSpec("step_height", "float32", NAN, "m", "largest height step to an 8-neighbour"),
    LayerSpec("traversability", "float32", NAN, "0..1", "1 = easy, 0 = impassable"),
    LayerSpec("occupancy", "float32", 0.0, "log-odds", "obstacle log-odds, 0 = unknown"),
    LayerSpec("entity_id", "int64", -1, "id", "entity frame id from SP, -1 = none"),
    LayerSpec("class_id", "int32", -1, "id", "class id from SP, -1 = none"),
    LayerSpec("cost", "float32", NAN, "", "traversal cost (value judgment)"),
    LayerSpec("confidence", "float32", 0.0, "0..1", "confidence in the elevation estimate"),
    LayerSpec("last_seen_ns", "int64", -1, "ns", "time the cell was last observed, -1 = never"),
)


#: Layers stored under an earlier name, old -> current, so that tiles in KD files written
#: before a rename still load. ``z_m2`` (Welford's M2) read as "z in square metres".
RENAMED_LAYERS: dict[str, str] = {"z_m2": "z_sq_dev_sum"}


def with_current_names(tile: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``tile`` (layer name -> array) with each layer stored under an earlier name
    (:data:`RENAMED_LAYERS`) under its current one: the same dict if it holds none, else a new
    one holding the same arrays. A tile holding both names keeps the current one's array."""
    if not any(old in tile for old in RENAMED_LAYERS):
        return tile
    out = dict(tile)
    for old, new in RENAMED_LAYERS.items():
        if old in out:
            out.setdefault(new, out.pop(old))
    return out


def layer_table(specs: tuple[LayerSpec, ...]) -> dict[str, LayerSpec]:
    """Specs by name; refuses duplicate names or dtypes numpy does not know."""
    table: dict[str, LayerSpec] = {}
    for spec in specs:
        if spec.name in table:
            raise LayerError(f"layer {spec.name!r} is specified twice")
        try:
            np.dtype(spec.dtype)
        except TypeError as exc:
            raise LayerError(f"layer {spec.name!r} has unknown dtype {spec.dtype!r}") from exc
        table[spec.name] = spec
    return table
