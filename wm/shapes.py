"""Entity shapes for prediction and collision checks: oriented boxes from KD entity frames.

An entity's box is centred on its state position (world frame, metres), turned by the yaw of
its orientation, with extents from its ``length_m`` / ``width_m`` / ``height_m`` attributes
(estimated, else observed, else the defaults below) - the attributes SP computes (reference
001, 4.5.3: attributes integrated over the group).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.geometry import quat_to_matrix, yaw_of
from kd_store import EntityFrame

DEFAULT_SIZE_M = (1.0, 1.0, 1.5)


@dataclass(frozen=True, slots=True)
class EntityBoxes:
    """Oriented boxes of M entities at one time, world frame.

    ids (M,) int64; centers_xyz (M, 3) m; sizes_lwh (M, 3) m full extents; yaws (M,) rad;
    velocities_xyz (M, 3) m/s; risks (M,) class risk; t_ns the time of the states.
    """

    ids: np.ndarray
    centers_xyz: np.ndarray
    sizes_lwh: np.ndarray
    yaws: np.ndarray
    velocities_xyz: np.ndarray
    risks: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def at(self, dt_s: np.ndarray) -> np.ndarray:
        """Centres (..., M, 3) after ``dt_s`` (...,) seconds at constant velocity."""
        dt = np.asarray(dt_s, dtype=np.float64)[..., None, None]
        return self.centers_xyz + dt * self.velocities_xyz

    @property
    def radii_m(self) -> np.ndarray:
        """(M,) radius of each box's footprint circle (half its x-y diagonal)."""
        return 0.5 * np.hypot(self.sizes_lwh[:, 0], self.sizes_lwh[:, 1])


def _attr(f: EntityFrame, name: str, default: float) -> float:
    a = f.attributes.get(name)
    if a is None:
        return default
    for v in (a.estimated, a.observed):
        if math.isfinite(v) and v > 0:
            return float(v)
    return default


def entity_size(f: EntityFrame) -> tuple[float, float, float]:
    """(length, width, height) metres of an entity (module docstring)."""
    d = DEFAULT_SIZE_M
    return (_attr(f, "length_m", d[0]), _attr(f, "width_m", d[1]), _attr(f, "height_m", d[2]))


def boxes_of(frames: list[EntityFrame], risks: list[float] | None = None) -> EntityBoxes:
    """Boxes of entity frames that have a world-frame state (others are left out)."""
    keep = [f for f in frames if f.state is not None and f.state.frame == "world"]
    m = len(keep)
    ids = np.array([f.id for f in keep], dtype=np.int64)
    centers = np.array([f.state.position_xyz for f in keep]).reshape(m, 3)  # type: ignore[union-attr]
    vel = np.array([f.state.velocity_xyz for f in keep]).reshape(m, 3)  # type: ignore[union-attr]
    yaws = np.array([yaw_of(quat_to_matrix(f.state.orientation_xyzw)) for f in keep])  # type: ignore[union-attr]
    sizes = np.array([entity_size(f) for f in keep]).reshape(m, 3)
    if risks is None:
        r = np.ones(m)
    else:
        by_id = dict(zip([f.id for f in frames], risks, strict=True))
        r = np.array([by_id[f.id] for f in keep], dtype=np.float64)
    return EntityBoxes(ids, centers, sizes, yaws.reshape(m), vel, r)
