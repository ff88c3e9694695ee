"""One map level: a square window of cells at one resolution around the vehicle, many layers.

Geometry (reference 001, 4.4.7; reference 000, Table 2: about 128 cells from the centre each way):

* The world is cut into a fixed grid of square cells of ``resolution_m``; cell ``(ix, iy)``
  (int64 global indices) covers ``x in [ix*res, (ix+1)*res)``, ``y in [iy*res, (iy+1)*res)``
  in the world frame. World coordinates never move: the vehicle moves over the grid.
* The window is ``size x size`` cells whose lower-left cell is ``origin_cell = (ix0, iy0)``.
  Window arrays are indexed ``[row, col]`` with ``row = iy - iy0`` (y, north) and
  ``col = ix - ix0`` (x, east), so row 0 is the southern edge.
* Storage is toroidal: cell ``(ix, iy)`` lives at ``storage[iy % size, ix % size]``. Moving the
  window by ``k`` cells clears only the ``k`` rows or columns that leave it; nothing is copied.
  :meth:`MapLevel.window` returns a layer in window order, with no wrap visible.

Cells leaving the window go to a :class:`~maps.tiles.TileStore` (if the level has one) and
come back from it when they re-enter, so a loop route restores the old map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.errors import EngineError
from maps.layers import (
    DEFAULT_LAYERS,
    LayerError,
    LayerSpec,
    layer_table,
    with_current_names,
)
from maps.tiles import Tile, TileKey, TileStore


class LevelError(EngineError, ValueError):
    """A level configuration or an argument that the level cannot take (names the value)."""


@dataclass(frozen=True)
class LevelConfig:
    """One level: name, cell edge ``resolution_m`` (metres), ``size`` cells per side, layers.

    ``tile_cells`` is the edge of a long-term-memory tile (cells); ``keep_tiles`` says whether
    cells leaving the window are kept in the level's tile store.
    """

    name: str = "subsystem"
    resolution_m: float = 0.4
    size: int = 256
    layers: tuple[LayerSpec, ...] = DEFAULT_LAYERS
    tile_cells: int = 64
    keep_tiles: bool = True

    def validate(self) -> LevelConfig:
        """Return self if usable, else raise :class:`LevelError` naming the bad field."""
        res = self.resolution_m
        if not (isinstance(res, int | float) and np.isfinite(res) and res > 0):
            raise LevelError(f"level {self.name!r}: resolution_m must be > 0 m, got {res!r}")
        if not (isinstance(self.size, int | np.integer) and self.size >= 2):
            raise LevelError(f"level {self.name!r}: size must be an int >= 2, got {self.size!r}")
        if self.tile_cells < 1:
            raise LevelError(f"level {self.name!r}: tile_cells must be >= 1, got {self.tile_cells}")
        return self


Range = tuple[int, int]  # (first global index, number of cells)


class MapLevel:
    """A rolling window of named layers at one resolution (see the module docstring)."""

    def __init__(self, config: LevelConfig | None = None, store: TileStore | None = None):
        self.config = (config or LevelConfig()).validate()
        self.size = int(self.config.size)
        self.resolution_m = float(self.config.resolution_m)
        try:
            self.specs = layer_table(self.config.layers)
        except LayerError as exc:
            raise LevelError(f"level {self.config.name!r}: {exc}") from exc
        self.store = store if self.config.keep_tiles else None
        shape = (self.size, self.size)
        self._data = {name: spec.empty(shape) for name, spec in self.specs.items()}
        self._fills = [(arr, self.specs[name].fill) for name, arr in self._data.items()]
        self._origin = (-(self.size // 2), -(self.size // 2))  # (ix0, iy0) as Python ints
        if self.store is not None:  # a store may already hold this window (an earlier run)
            self._load((self._origin[0], self.size), (self._origin[1], self.size))

    @property
    def origin_cell(self) -> np.ndarray:
        """Global cell ``(ix0, iy0)`` (int64 (2,)) of window row 0, column 0."""
        return np.array(self._origin, dtype=np.int64)

    @origin_cell.setter
    def origin_cell(self, cell: np.ndarray) -> None:
        """Put the window's lower-left cell at ``cell`` without clearing (for aligned copies)."""
        self._origin = (int(cell[0]), int(cell[1]))

    # --- names and shapes ------------------------------------------------------------------

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def layer_names(self) -> list[str]:
        return list(self._data)

    def storage(self, layer: str) -> np.ndarray:
        """The raw toroidal array of ``layer`` (size, size): index it with storage indices."""
        try:
            return self._data[layer]
        except KeyError:
            raise LevelError(
                f"level {self.name!r} has no layer {layer!r}; valid layers: {self.layer_names}"
            ) from None

    def require(self, *layers: str) -> None:
        """Raise :class:`LevelError` unless every named layer exists."""
        for layer in layers:
            self.storage(layer)

    # --- index transforms ------------------------------------------------------------------

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """World ``(N, 2)`` metres -> global cell indices ``(N, 2)`` int64 ``(ix, iy)``."""
        xy = self._xy(xy, "xy")
        return np.floor(xy / self.resolution_m).astype(np.int64)

    def cell_to_world(self, cells: np.ndarray) -> np.ndarray:
        """Global cell indices ``(N, 2)`` ``(ix, iy)`` -> cell centres ``(N, 2)`` metres."""
        return (np.asarray(cells, dtype=np.float64) + 0.5) * self.resolution_m

    def world_to_window(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World ``(N, 2)`` -> ``(rows, cols, inside)``: window indices (int64) and a mask."""
        cells = self.world_to_cell(xy) - self.origin_cell
        cols, rows = cells[:, 0], cells[:, 1]
        inside = (rows >= 0) & (rows < self.size) & (cols >= 0) & (cols < self.size)
        return rows, cols, inside

    def window_to_world(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Window indices -> cell centres ``(N, 2)`` metres in the world frame."""
        cells = np.stack(
            [np.asarray(cols) + self.origin_cell[0], np.asarray(rows) + self.origin_cell[1]],
            axis=-1,
        )
        return self.cell_to_world(cells)

    def window_to_storage(
        self, rows: np.ndarray, cols: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Window indices -> storage indices ``(srow, scol)`` into :meth:`storage` arrays."""
        return (
            (np.asarray(rows) + self.origin_cell[1]) % self.size,
            (np.asarray(cols) + self.origin_cell[0]) % self.size,
        )

    @property
    def center_xy(self) -> np.ndarray:
        """World position (metres) of the window centre (corner of the 4 middle cells)."""
        return (self.origin_cell + self.size // 2).astype(np.float64) * self.resolution_m

    @property
    def bounds_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """World ``(xy_min, xy_max)`` of the window, metres."""
        lo = self.origin_cell.astype(np.float64) * self.resolution_m
        return lo, lo + self.size * self.resolution_m

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """Mask ``(N,)``: which world points fall inside the window."""
        return self.world_to_window(xy)[2]

    # --- reading and writing ---------------------------------------------------------------

    def window(self, layer: str) -> np.ndarray:
        """A copy of ``layer`` in window order ``[row, col]`` (row 0 south), no wrap visible."""
        return self.to_window(self.storage(layer))

    def to_window(self, arr: np.ndarray) -> np.ndarray:
        """A copy of ``arr`` (size, size), laid out as this level's storage, in window order."""
        shift = (-int(self.origin_cell[1] % self.size), -int(self.origin_cell[0] % self.size))
        return np.roll(arr, shift, axis=(0, 1))

    def set_window(self, layer: str, values: np.ndarray) -> None:
        """Replace ``layer`` with ``values`` given in window order (size, size)."""
        arr = self.storage(layer)
        values = np.asarray(values)
        if values.shape != arr.shape:
            raise LevelError(
                f"level {self.name!r}: layer {layer!r} needs shape {arr.shape}, got {values.shape}"
            )
        shift = (int(self.origin_cell[1] % self.size), int(self.origin_cell[0] % self.size))
        arr[...] = np.roll(values, shift, axis=(0, 1))

    def read(self, layer: str, xy: np.ndarray) -> np.ndarray:
        """Values of ``layer`` at world points ``(N, 2)``; the layer's fill outside the window."""
        arr = self.storage(layer)
        rows, cols, inside = self.world_to_window(xy)
        out = np.full(rows.shape, self.specs[layer].fill, dtype=arr.dtype)
        srow, scol = self.window_to_storage(rows[inside], cols[inside])
        out[inside] = arr[srow, scol]
        return out

    def write(self, layer: str, xy: np.ndarray, values: np.ndarray | float) -> int:
        """Write ``values`` (scalar or (N,)) at world points ``(N, 2)`` inside the window.

        Points outside the window are ignored; returns how many were written. Where several
        points hit one cell the last one wins.
        """
        arr = self.storage(layer)
        rows, cols, inside = self.world_to_window(xy)
        vals = np.asarray(values, dtype=arr.dtype)
        if vals.ndim > 0:
            if vals.shape != rows.shape:
                raise LevelError(
                    f"level {self.name!r}: {rows.shape[0]} points but values of shape {vals.shape}"
                )
            vals = vals[inside]
        srow, scol = self.window_to_storage(rows[inside], cols[inside])
        arr[srow, scol] = vals
        return int(np.count_nonzero(inside))

    def clear(self) -> None:
        """Empty every layer (the window stays where it is; nothing goes to the tile store)."""
        for name, arr in self._data.items():
            arr.fill(self.specs[name].fill)

    # --- moving ----------------------------------------------------------------------------

    def origin_for(self, center_xy: np.ndarray) -> tuple[int, int]:
        """The ``origin_cell`` ``(ix0, iy0)`` that puts world ``center_xy`` in the middle."""
        try:
            x, y = float(center_xy[0]), float(center_xy[1])
        except (TypeError, IndexError, ValueError):
            x = y = math.nan
        if not (math.isfinite(x) and math.isfinite(y)):
            raise LevelError(
                f"level {self.name!r}: center_xy must be a finite (x, y), got {center_xy!r}"
            )
        half = self.size // 2
        return math.floor(x / self.resolution_m) - half, math.floor(y / self.resolution_m) - half

    def move_to(self, center_xy: np.ndarray) -> tuple[int, int]:
        """Scroll the window so ``center_xy`` (world metres) is in its middle cell.

        Only cells leaving the window are cleared (after going to the tile store, if any) and
        cells entering come back from the store. A jump of a whole window or more (a teleport)
        clears the level. Returns the move ``(dx, dy)`` in cells.
        """
        (ox, oy), new = self._origin, self.origin_for(center_xy)
        dx, dy = new[0] - ox, new[1] - oy
        if dx == 0 and dy == 0:
            return 0, 0
        size = self.size
        if abs(dx) >= size or abs(dy) >= size:
            self._teleport(new)
            return dx, dy
        if self.store is None:  # the hot path: clear the slots of the entering strips only
            if dx:
                self._clear_slots((ox + size if dx > 0 else ox + dx, abs(dx)), axis=1)
            if dy:
                self._clear_slots((oy + size if dy > 0 else oy + dy, abs(dy)), axis=0)
            self._origin = new
            return dx, dy
        leave_x, enter_x, keep_x = _split(ox, dx, size)
        leave_y, enter_y, _ = _split(oy, dy, size)
        if self.store is not None:
            self._save(leave_x, (oy, size))
            self._save(keep_x, leave_y)
        if dx:
            self._clear_slots(enter_x, axis=1)
        if dy:
            self._clear_slots(enter_y, axis=0)
        self._origin = new
        if self.store is not None:
            self._load(enter_x, (new[1], size))
            self._load(keep_x, enter_y)
        return dx, dy

    def _teleport(self, new: tuple[int, int]) -> None:
        (ox, oy), size = self._origin, self.size
        if self.store is not None:
            self._save((ox, size), (oy, size))
        self.clear()
        self._origin = new
        if self.store is not None:
            self._load((new[0], size), (new[1], size))

    def _clear_slots(self, cells: Range, axis: int) -> None:
        """Fill the storage rows (axis 0) or columns (axis 1) of global indices ``cells``."""
        lo, n = cells
        if n <= 0:
            return
        size = self.size
        s = lo % size
        if s + n <= size:
            slices = (slice(s, s + n),)
        else:  # the strip wraps round the storage edge
            slices = (slice(s, size), slice(0, s + n - size))
        for sl in slices:
            key = (slice(None), sl) if axis == 1 else sl
            for arr, fill in self._fills:
                arr[key] = fill

    # --- long-term memory ------------------------------------------------------------------

    def _tiles_over(self, rx: Range, ry: Range):
        """Yield ``(tx, ty, ix_lo, ix_hi, iy_lo, iy_hi)`` for tiles meeting the global box."""
        t = self.config.tile_cells
        if rx[1] <= 0 or ry[1] <= 0:
            return
        for ty in range(ry[0] // t, (ry[0] + ry[1] - 1) // t + 1):
            iy_lo, iy_hi = max(ry[0], ty * t), min(ry[0] + ry[1], (ty + 1) * t)
            for tx in range(rx[0] // t, (rx[0] + rx[1] - 1) // t + 1):
                ix_lo, ix_hi = max(rx[0], tx * t), min(rx[0] + rx[1], (tx + 1) * t)
                yield tx, ty, ix_lo, ix_hi, iy_lo, iy_hi

    def keep_window(self) -> int:
        """Put the whole current window into the tile store (e.g. at the end of a run, so a
        later level over the same store starts from it); returns the tiles put."""
        if self.store is None:
            return 0
        (ox, oy), size = self._origin, self.size
        return self._save((ox, size), (oy, size))

    def _save(self, rx: Range, ry: Range) -> int:
        """Copy the cells of global box ``rx x ry`` (inside the window) into the tile store,
        merged into the tiles already there; returns the tiles put."""
        t = self.config.tile_cells
        n_put = 0
        for tx, ty, ix_lo, ix_hi, iy_lo, iy_hi in self._tiles_over(rx, ry):
            cells = self._storage_box(ix_lo, ix_hi, iy_lo, iy_hi)
            blocks = {n: a[cells] for n, a in self._data.items()}  # views, copied below
            key = (self.name, tx, ty)
            tile = self._stored(key)
            if tile is None:
                if all(_is_fill(b, self.specs[n].fill) for n, b in blocks.items()):
                    continue
                tile = {n: s.empty((t, t)) for n, s in self.specs.items()}
            r0, c0 = iy_lo - ty * t, ix_lo - tx * t
            for n, b in blocks.items():
                if n not in tile:  # a layer the stored tile was written without
                    tile[n] = self.specs[n].empty((t, t))
                tile[n][r0 : r0 + b.shape[0], c0 : c0 + b.shape[1]] = b
            self.store.put(key, tile)
            n_put += 1
        return n_put

    def _load(self, rx: Range, ry: Range) -> None:
        """Fill the cells of global box ``rx x ry`` from tiles the store holds."""
        t = self.config.tile_cells
        for tx, ty, ix_lo, ix_hi, iy_lo, iy_hi in self._tiles_over(rx, ry):
            tile = self._stored((self.name, tx, ty))
            if tile is None:
                continue
            cells = self._storage_box(ix_lo, ix_hi, iy_lo, iy_hi)
            r0, c0 = iy_lo - ty * t, ix_lo - tx * t
            for n, a in self._data.items():
                if n in tile:
                    a[cells] = tile[n][r0 : r0 + iy_hi - iy_lo, c0 : c0 + ix_hi - ix_lo]

    def _stored(self, key: TileKey) -> Tile | None:
        """The store's tile ``key`` with its layers under their current names (a KD file
        written before a layer was renamed holds the old name), or None if it has none."""
        tile = self.store.get(key)
        return None if tile is None else with_current_names(tile)

    def _storage_box(self, ix_lo: int, ix_hi: int, iy_lo: int, iy_hi: int) -> Any:
        """Index of the storage cells of global box ``[ix_lo, ix_hi) x [iy_lo, iy_hi)``
        (inside the window): plain slices (views, no gather) unless the box wraps round the
        storage edge, which a tile never does when its edge divides the level's size."""
        size = self.size
        r0, c0 = iy_lo % size, ix_lo % size
        r1, c1 = r0 + iy_hi - iy_lo, c0 + ix_hi - ix_lo
        if r1 <= size and c1 <= size:
            return slice(r0, r1), slice(c0, c1)
        return np.ix_(np.arange(iy_lo, iy_hi) % size, np.arange(ix_lo, ix_hi) % size)

    # --- helpers ---------------------------------------------------------------------------

    def _xy(self, xy: np.ndarray, what: str) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] < 2:
            raise LevelError(
                f"level {self.name!r}: {what} must be (N, 2) or (N, 3), got {xy.shape}"
            )
        return xy[:, :2]


def _split(lo: int, d: int, size: int) -> tuple[Range, Range, Range]:
    """For a window ``[lo, lo+size)`` moving by ``d`` (``|d| < size``): leaving, entering and
    kept global index ranges along one axis."""
    if d >= 0:
        return (lo, d), (lo + size, d), (lo + d, size - d)
    return (lo + size + d, -d), (lo + d, -d), (lo, size + d)


def _is_fill(block: np.ndarray, fill: float | int) -> bool:
    if isinstance(fill, float) and np.isnan(fill):
        return bool(np.isnan(block).all())
    return bool((block == fill).all())
