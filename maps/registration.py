"""Registration of a local map against an a priori or earlier map by pyramid correlation.

Reference 001, 4.4.7: "local maps generated from camera data can be registered with a priori
maps"; 4.5.5: coarse-to-fine correlation over a pyramid of scale, 9 offsets per level, then a
sub-pixel peak. The correlation itself is :func:`maps.pyramid.register`; this module lines the
two maps up on one world grid, masks cells with no data, and turns the pixel shift into a
world offset with a confidence usable for drift correction.

Sign convention: ``offset_xy_m`` is how far the moving map's content sits from the
reference's, along world x and y: a feature at ``p`` in the reference appears at
``p + offset_xy_m`` in the moving map. To correct a drifting local map (and the poses that
built it), move it by ``-offset_xy_m``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from core.errors import EngineError
from maps.apriori import ElevationRaster, write_raster
from maps.level import MapLevel
from maps.pyramid import register
from maps.terrain import step_heights


class RegistrationError(EngineError, ValueError):
    """Two maps that cannot be registered as asked (names what differs)."""


@dataclass(frozen=True)
class MapRegistration:
    """Result: world ``offset_xy_m`` (2,) metres, window ``shift_rc`` (2,) cells, the peak
    normalised correlation (-1..1), a ``confidence`` (0..1) and the cells both maps know."""

    offset_xy_m: np.ndarray
    shift_rc: np.ndarray
    peak: float
    confidence: float
    overlap_cells: int


def register_levels(
    reference: MapLevel,
    moving: MapLevel,
    *,
    layer: str = "elevation",
    pyramid_levels: int = 4,
    max_shift_m: float | None = None,
    min_overlap_cells: int = 64,
    max_step_m: float | None = 0.7,
) -> MapRegistration:
    """Register ``moving`` against ``reference`` (same resolution) over the reference window.

    Cells with no value (NaN) in either map take no part. A flat offset in height (e.g. a
    different datum) does not matter: correlation is normalised. Cells with a step of more
    than ``max_step_m`` to a neighbour are left out of both maps: fusion gates points on
    such steps as obstacles, so a sensed map has holes there that a raster has not, and holes
    in one map only pull the peak off the true offset (on the AV2 raster by about a cell).
    The default 0.7 m is fusion's default gate over a 0.6 m cell diagonal; None keeps all.
    Confidence is 0 when fewer than ``min_overlap_cells`` cells are known in both maps.
    """
    if not np.isclose(reference.resolution_m, moving.resolution_m):
        raise RegistrationError(
            f"maps must share a resolution: reference {reference.name!r} "
            f"{reference.resolution_m} m, moving {moving.name!r} {moving.resolution_m} m"
        )
    ref = reference.window(layer).astype(np.float64)
    rr, cc = np.nonzero(np.ones(ref.shape, dtype=bool))
    mov = moving.read(layer, reference.window_to_world(rr, cc)).astype(np.float64)
    mov = mov.reshape(ref.shape)
    if max_step_m is not None:  # steep steps: left out of both maps alike (see docstring)
        ref[step_heights(ref) > max_step_m] = np.nan
        mov[step_heights(mov) > max_step_m] = np.nan
    ok_ref, ok_mov = np.isfinite(ref), np.isfinite(mov)
    overlap = int(np.count_nonzero(ok_ref & ok_mov))
    res = reference.resolution_m
    if overlap < min_overlap_cells:
        zero = np.zeros(2)
        return MapRegistration(zero, zero.copy(), 0.0, 0.0, overlap)
    ref = np.where(ok_ref, ref - np.mean(ref[ok_ref]), 0.0)
    mov = np.where(ok_mov, mov - np.mean(mov[ok_mov]), 0.0)
    match = register(
        ref,
        mov,
        levels=pyramid_levels,
        max_shift_px=None if max_shift_m is None else max_shift_m / res,
        valid_reference=ok_ref,
        valid_moving=ok_mov,
    )
    shift = np.asarray(match.shift_rc, dtype=np.float64)
    offset = np.array([shift[1], shift[0]]) * res  # rows are y, columns x
    return MapRegistration(offset, shift, float(match.peak), float(match.confidence), overlap)


def register_to_raster(
    level: MapLevel, raster: ElevationRaster, **kwargs: float | int | str | None
) -> MapRegistration:
    """Register ``level``'s elevation (moving) against an a priori raster (reference), sampled
    onto the level's own grid and window. Keyword arguments go to :func:`register_levels`."""
    prior = MapLevel(replace(level.config, keep_tiles=False))
    prior.origin_cell = level.origin_cell.copy()
    write_raster(prior, raster, variance_m2=0.0, only_empty=False)
    return register_levels(prior, level, **kwargs)
