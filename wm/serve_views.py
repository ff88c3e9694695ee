"""Views of the live node beyond What Is, for :mod:`wm.serve`: map windows, the entities of
attention per level, and a push stream of what each cycle changed.

    GET /v1/maps/{level}?x=&y=&half_m=&layers=elevation,cost
    GET /v1/attention?level=4
    GET /v1/stream                    (server-sent events, one per node cycle)

Map windows (:func:`map_window`): the cells of one map level (``primitive``, ``subsystem``,
``vehicle``, ``section``, or their reference-model numbers 2..5) around a world point, as the
node's maps hold them between two cycles: read from the newest cycle's copy when it holds the
layers (What If's four, and those asked for in the last 30 s), else under the node's lock
(:func:`read_level`; :mod:`wm.serve_copy`). A layer's earlier name (``z_m2``,
:data:`maps.layers.RENAMED_LAYERS`) is taken for its current one (``z_sq_dev_sum``): the answer
names the layer by the current name and says so in ``renamed_layers`` ({earlier: current}; in
every format's metadata) and the header :data:`RENAMED_HEADER`. The window is the ``(2k+1) x
(2k+1)`` cells centred on the cell holding (x, y), ``k = ceil(half_m / resolution_m)``; row 0 is
the southern edge, column 0 the western one (as :class:`maps.level.MapLevel`), ``origin`` is the
world (x, y) in metres of the south-west corner of cell [0, 0]. Cells outside the level's
current window (it scrolls with the vehicle) hold the layer's empty value (NaN, -1 or 0, as
``maps.layers`` says): the server does not read the KD's stored tiles. JSON answers (lists, NaN
as null) are for small windows (:data:`MAX_JSON_VALUES`); ``Accept: application/x-npy`` gives
one ``.npy`` array (layers, rows, cols) float64 with the metadata in ``X-Map-*`` headers,
``Accept: application/vnd.apache.arrow.stream`` an Arrow IPC stream with one row per cell
(``row``, ``col``, cell-centre ``x``, ``y`` world m, then one column per layer in its own dtype)
and the metadata in the schema's; both up to :data:`MAX_BINARY_VALUES` values (cells x layers).

Entities of attention (:func:`attention_entities`) of SP level L (1..5, or a map level's name,
which stands for the SP level of the same number): the entities of level L, neither denied nor
gone, that the node attends to, each with the reasons why (worked out at the end of every
cycle for the levels asked for in the last 30 s, so answered from the cycle's copy; the first
request for a level works it out under the node's lock):

* ``"attention list"``: on the entities-of-attention list value judgment keeps for the node
  level of L (``kd.attention``, written by the node's step 5 from proximity, danger, novelty
  and relevance to the plan; the rank is given);
* ``"predicted window"``: level 4 only; SP tracks it, so its predicted position opens a window
  on the next sweep (sp.level4_objects ``ObjectLevel.window``; the window's half-size grows with the
  position's standard deviation, given in metres);
* ``"surprise window"``: a point the range-image prediction got wrong last cycle (the node's
  ``attention_world_xyz``) lies within the window base (1 m) plus the entity's size;
* ``"hypothesis awaiting confirmation"``: it is hypothesized (SP keeps attending to the pixels
  of new and provisional hypotheses).

The push stream (:class:`CycleDiff` where the node runs, :class:`CycleFeed` in the server): at
the end of every node cycle the entities it created, changed (a new state, status, class or
confidence) and ended (denied, gone, or forgotten from short-term memory), and the events it
made, as one ``event: cycle`` of server-sent events.
Every client has a queue of :data:`STREAM_QUEUE_CYCLES` cycles; the node only appends to it and
never waits for a reader: when a queue is full its oldest cycle is dropped and counted, and the
next message the client gets says how many (``dropped``). When the replay ends, a client gets
``event: end`` after the last cycle. ``/v1/status`` carries ``stream`` (clients, cycles
published, cycles dropped over all clients).
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import logging
import math
import threading
from collections import deque
from collections.abc import AsyncIterator, Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Annotated, Any, TypeVar

import numpy as np
from fastapi import FastAPI, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response, StreamingResponse

from maps.layers import RENAMED_LAYERS
from wm.serve_copy import attention_key, layer_key

log = logging.getLogger(__name__)
T = TypeVar("T")

MAX_JSON_VALUES = 10_000  # cells x layers of one JSON map window
MAX_BINARY_VALUES = 1_000_000  # ... of one .npy or Arrow map window (8 MB as float64)
MAX_COORD_M = 1e9  # |x|, |y| of a position asked about, m: beyond any map, cell indices exact
STREAM_QUEUE_CYCLES = 64  # cycles one stream client may fall behind before the oldest drop
STREAM_POLL_S = 0.02  # how often an idle stream looks at its queue, s
STREAM_KEEPALIVE_S = 5.0  # an SSE comment after this long without a message, s
NPY = "application/x-npy"
ARROW_STREAM = "application/vnd.apache.arrow.stream"
# reference-model numbers of the default map levels (wm/render.py names its pictures so)
MAP_LEVEL_NUMBERS = {2: "primitive", 3: "subsystem", 4: "vehicle", 5: "section"}
ENDED = ("denied", "gone")
RENAMED_HEADER = "X-Map-Renamed-Layers"  # "old=new,...": layers asked by an earlier name


# --- map windows -------------------------------------------------------------------------------


@dataclass(frozen=True)
class MapWindow:
    """Cells of one level around a point: ``values[name]`` (rows, cols) in the layer's dtype,
    row 0 south; ``origin_xy`` the world (x, y) m of cell [0, 0]'s south-west corner;
    ``level_bounds`` the level's current window ((x_min, y_min), (x_max, y_max)) world m."""

    level: str
    resolution_m: float
    origin_xy: tuple[float, float]
    values: dict[str, np.ndarray]
    level_bounds: tuple[tuple[float, float], tuple[float, float]]

    @property
    def shape(self) -> tuple[int, int]:
        return next(iter(self.values.values())).shape


def find_level(stack: Any, key: str) -> Any:
    """The stack's level named ``key``, or numbered so (2..5, :data:`MAP_LEVEL_NUMBERS`);
    HTTP 404 naming the key and the levels there are."""
    # ASCII decimal digits only: "²" is a digit to isdigit() but int() refuses it
    name = MAP_LEVEL_NUMBERS.get(int(key), key) if key.isascii() and key.isdecimal() else key
    for lvl in stack.levels:
        if lvl.name == name:
            return lvl
    have = [f"{n} ({lvl})" for n, lvl in MAP_LEVEL_NUMBERS.items()]
    raise HTTPException(404, f"map level {key!r}: unknown; the levels are {have}")


def window_span(resolution_m: float, c: float, half_m: float) -> tuple[int, int]:
    """``(i0, n)`` along one axis: the global index of the window's first cell and its cells,
    ``n = 2k+1`` around the cell holding world coordinate ``c`` m, ``k = ceil(half_m / res)``."""
    k = math.ceil(half_m / resolution_m)
    return math.floor(c / resolution_m) - k, 2 * k + 1


def window_cells(resolution_m: float, x: float, y: float, half_m: float) -> tuple[int, int, int]:
    """``(ix0, iy0, n)``: the global index of the window's south-west cell and its cells per
    side, ``n = 2k+1`` around the cell holding world (x, y) m, ``k = ceil(half_m / res)``."""
    (ix0, n), (iy0, _) = window_span(resolution_m, x, half_m), window_span(resolution_m, y, half_m)
    return ix0, iy0, n


def level_layers(level: Any) -> list[str]:
    """Every layer of ``level`` (a :class:`maps.level.MapLevel`, or a copy of some of its
    layers, :class:`wm.whatif.LevelCopy`): the level's configuration names them."""
    return [spec.name for spec in level.config.layers]


def resolve_layers(level: Any, names: Sequence[str]) -> tuple[list[str], dict[str, str]]:
    """``names`` as layers of ``level``, each once in the order asked, an earlier name
    (:data:`maps.layers.RENAMED_LAYERS`, e.g. ``z_m2``) standing for its current one; and
    {earlier: current} for those so asked. HTTP 400 naming the unknown ones."""
    have = level_layers(level)
    renamed = {n: RENAMED_LAYERS[n] for n in names
               if n not in have and RENAMED_LAYERS.get(n) in have}  # fmt: skip
    unknown = [n for n in names if n not in have and n not in renamed]
    if unknown:
        earlier = ", ".join(f"{old} (now {new})" for old, new in RENAMED_LAYERS.items())
        raise HTTPException(
            400,
            f"layers {unknown}: unknown on level {level.name!r}; known: {have}; earlier names "
            f"taken: {earlier}",
        )
    return list(dict.fromkeys(renamed.get(n, n) for n in names)), renamed


@dataclass(frozen=True)
class LevelRead:
    """A map level to answer from, with the layers asked and the cycle it is as of
    (``cycle_t_ns``, int64 ns of log time; -1 before the first cycle): a level of the cycle's
    copy (``snapshot``, a :class:`wm.serve.CycleSnapshot`; ``node`` None), or the node's own
    level under its lock (``node``, the :class:`~wm.node.WorldModelNode`; ``snapshot``
    None), to read only while the lock is held."""

    level: Any
    layers: list[str]
    cycle_t_ns: int
    snapshot: Any | None
    node: Any | None


def running_node(live: Any) -> Any:
    """The live node (None when it runs in a process of its own); HTTP 503 when it is not
    running (not started, stopped, or its process gone)."""
    if not live.running:
        raise HTTPException(503, "the live node is not running (not started, or stopped)")
    return live.node


def read_level(
    live: Any,
    key: str,
    layers_of: Callable[[Any], list[str]],
    read: Callable[[LevelRead], T],
    entities: bool = False,
) -> T:
    """``read`` over map level ``key`` (:func:`find_level`) of the newest cycle, with the
    layers ``layers_of(level)`` names (it checks the request too; its HTTP errors pass).

    From the cycle's copy (:class:`wm.serve.CycleSnapshot`) when it holds every layer named:
    no lock, so the request neither waits for the cycle in progress nor holds it up. Else
    (the first request for a layer, or one beyond the copy's byte limit: :mod:`wm.serve_copy`)
    under the node's lock from the node's own level; for a node in a process of its own, from
    a copy of those layers the node makes under its lock (:func:`copy_level`; ``entities``:
    with what What If reads of the KD, for ``read`` to check against). Either way the layers
    are asked for (:class:`wm.serve_copy.ServedDemand`), so the cycles after copy them."""
    if (answer := read_level_copy(live, key, layers_of, read)) is not None:
        return answer[0]
    return read_level_node(live, key, layers_of, read, entities)


def read_level_node(
    live: Any,
    key: str,
    layers_of: Callable[[Any], list[str]],
    read: Callable[[LevelRead], T],
    entities: bool = False,
) -> T:
    """:func:`read_level` from the node: the copy of the layers its process makes, or its own
    level under its lock. Waits for the node: call it from a worker thread."""
    snap = live.snapshot
    if live.process:
        levels = snap.maps if snap is not None and snap.maps is not None else live.map_levels
        if levels is None:
            raise HTTPException(503, "the live node keeps no maps (its KD is in memory)")
        lvl = find_level(levels, key)
        names = layers_of(lvl)
        live.demand.ask(layer_key(lvl.name, n) for n in names)
        from wm.serve import ServeError

        try:
            copy, cycle, over = live.call(copy_level, lvl.name, names, entities)
        except ServeError as e:
            raise HTTPException(503, str(e)) from None
        return read(LevelRead(copy, names, cycle, over, None))
    with live.lock:
        node = running_node(live)
        if node.stack is None:
            raise HTTPException(503, "the live node keeps no maps (its KD is in memory)")
        snap = live.snapshot  # set under the lock with the cycle, unlike ``live.status``
        lvl = find_level(node.stack, key)
        names = layers_of(lvl)
        live.demand.ask(layer_key(lvl.name, n) for n in names)
        cycle = snap.cycle_t_ns if snap is not None else -1
        return read(LevelRead(lvl, names, cycle, None, node))


def read_level_copy(
    live: Any, key: str, layers_of: Callable[[Any], list[str]], read: Callable[[LevelRead], T]
) -> tuple[T] | None:
    """(``read`` over map level ``key``,) from the cycle's copy when it holds every layer
    ``layers_of`` names (those are asked for either way), else None: :func:`read_level`'s
    answer when it needs neither the node nor its lock."""
    snap = live.snapshot  # one read: a cycle ending now replaces it whole
    running_node(live)
    if snap is None or snap.maps is None:
        return None
    lvl = find_level(snap.maps, key)
    names = layers_of(lvl)
    live.demand.ask(layer_key(lvl.name, n) for n in names)
    if not all(n in lvl.specs for n in names):
        return None
    return (read(LevelRead(lvl, names, snap.cycle_t_ns, snap, None)),)


def copy_level(live: Any, name: str, layers: list[str], entities: bool) -> tuple[Any, int, Any]:
    """(the ``layers`` of map level ``name`` as a :class:`wm.whatif.LevelCopy`, the newest
    cycle's time, a :class:`wm.serve.CycleSnapshot` holding only what What If reads of the KD
    when ``entities``, else None), copied under the node's lock between two cycles: what
    :func:`read_level` reads for a node in a process of its own when the cycle's copy lacks a
    layer (a :meth:`wm.serve.LiveNode.call`)."""
    from wm.serve import CycleSnapshot, served_config
    from wm.whatif import LevelCopy, WhatIfCopy

    with live.lock:
        node = running_node(live)
        if node.stack is None:
            raise HTTPException(503, "the live node keeps no maps (its KD is in memory)")
        snap = live.snapshot
        cycle = snap.cycle_t_ns if snap is not None else -1
        copy = LevelCopy(find_level(node.stack, name), tuple(layers))
        over = None
        if entities:  # no map level: What If's entities only
            wi = WhatIfCopy.of(node.kd, node.stack, node.self_id, ())
            config = served_config(node.engine_config)
            over = CycleSnapshot(cycle, node.self_id, {}, {}, wi, config)
    return copy, cycle, over


def map_window(
    level: Any, x: float, y: float, half_m: float, layers: list[str], half_y_m: float | None = None
) -> MapWindow:
    """The ``layers`` of ``level`` (a :class:`maps.level.MapLevel`) in the window around world
    (x, y) m of half-width ``half_m`` m (module docstring); ``half_y_m``, if given, is the
    half-height (along y) of a rectangular window, ``half_m`` then the half-width along x.
    Cells outside the level's current window hold the layer's empty value. Call it between two
    of the node's cycles, or on a level of the cycle's copy (:func:`read_level`)."""
    res = level.resolution_m
    ix0, nx = window_span(res, x, half_m)
    iy0, ny = window_span(res, y, half_m if half_y_m is None else half_y_m)
    # offsets into the level's window, clamped (a window far beyond the level lies wholly
    # outside it either way) so that a centre of 1e300 m does not overflow int64
    r0 = min(max(iy0 - int(level.origin_cell[1]), -ny), level.size)
    c0 = min(max(ix0 - int(level.origin_cell[0]), -nx), level.size)
    rows = np.arange(ny, dtype=np.int64) + r0
    cols = np.arange(nx, dtype=np.int64) + c0
    r_in = (rows >= 0) & (rows < level.size)
    c_in = (cols >= 0) & (cols < level.size)
    srow, scol = level.window_to_storage(rows[r_in], cols[c_in])
    out = {}
    for name in layers:
        arr = level.storage(name)
        vals = np.full((ny, nx), level.specs[name].fill, dtype=arr.dtype)
        # the level's storage is toroidal: index it cell by cell, no copy of the whole layer
        vals[np.ix_(r_in, c_in)] = arr[np.ix_(srow, scol)]
        out[name] = vals
    lo, hi = level.bounds_xy
    bounds = ((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])))
    return MapWindow(level.name, res, (ix0 * res, iy0 * res), out, bounds)


def _layer_json(a: np.ndarray) -> list:
    """Rows of ``a`` as lists, NaN and infinities as null (JSON has no words for them)."""
    if a.dtype.kind != "f":
        return a.tolist()
    obj = a.astype(object)
    obj[~np.isfinite(a)] = None
    return obj.tolist()


def _window_meta(w: MapWindow, cycle_t_ns: int, renamed: dict[str, str]) -> dict:
    return {
        "level": w.level,
        "frame": "world",
        "cycle_t_ns": cycle_t_ns,
        "resolution_m": w.resolution_m,
        "origin": list(w.origin_xy),
        "shape": list(w.shape),
        "layers": list(w.values),
        "level_bounds": [list(w.level_bounds[0]), list(w.level_bounds[1])],
        # layers asked by an earlier name, answered under the current one: {earlier: current}
        "renamed_layers": dict(renamed),
    }


def renamed_headers(renamed: dict[str, str]) -> dict[str, str]:
    """:data:`RENAMED_HEADER` (``old=new,...``) when layers were asked by an earlier name."""
    if not renamed:
        return {}
    return {RENAMED_HEADER: ",".join(f"{old}={new}" for old, new in renamed.items())}


def _npy_response(w: MapWindow, cycle_t_ns: int, renamed: dict[str, str]) -> Response:
    """The layers stacked (L, rows, cols) float64 as one .npy; metadata in headers."""
    buf = io.BytesIO()
    np.save(buf, np.stack([v.astype(np.float64) for v in w.values.values()]))
    meta = _window_meta(w, cycle_t_ns, renamed)
    headers = renamed_headers(renamed) | {
        "X-Map-Level": w.level,
        "X-Map-Layers": ",".join(w.values),
        "X-Map-Origin": f"{w.origin_xy[0]!r},{w.origin_xy[1]!r}",
        "X-Map-Resolution-M": repr(w.resolution_m),
        "X-Map-Frame": "world",
        "X-Map-Shape": ",".join(str(s) for s in (len(w.values), *w.shape)),
        "X-Cycle-T-Ns": str(cycle_t_ns),
        "X-Map-Meta": json.dumps(meta),
    }
    return Response(buf.getvalue(), media_type=NPY, headers=headers)


def _arrow_response(w: MapWindow, cycle_t_ns: int, renamed: dict[str, str]) -> Response:
    """One row per cell: row, col, cell-centre x, y (world m), one column per layer."""
    import pyarrow as pa

    n_rows, n_cols = w.shape
    row, col = np.meshgrid(np.arange(n_rows), np.arange(n_cols), indexing="ij")
    cols = {
        "row": row.reshape(-1).astype(np.int32),
        "col": col.reshape(-1).astype(np.int32),
        "x": w.origin_xy[0] + (col.reshape(-1) + 0.5) * w.resolution_m,
        "y": w.origin_xy[1] + (row.reshape(-1) + 0.5) * w.resolution_m,
    } | {name: v.reshape(-1) for name, v in w.values.items()}
    return arrow_response(pa.table(cols), _window_meta(w, cycle_t_ns, renamed),
                          renamed_headers(renamed))  # fmt: skip


def arrow_response(table: Any, meta: dict[str, Any], headers: dict[str, str]) -> Response:
    """``table`` (a ``pyarrow.Table``) as one Arrow IPC stream, ``meta`` (JSON values) added
    to its schema's metadata, with ``headers``."""
    import pyarrow as pa

    table = table.replace_schema_metadata(
        {**(table.schema.metadata or {}), **{k: json.dumps(v) for k, v in meta.items()}}
    )
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return Response(sink.getvalue().to_pybytes(), media_type=ARROW_STREAM, headers=headers)


def _wanted_layers(level: Any, layers: str) -> tuple[list[str], dict[str, str]]:
    """The layers a comma-separated ``layers`` names (:func:`resolve_layers`); 400 for none."""
    names = [s.strip() for s in layers.split(",") if s.strip()]
    if not names:
        raise HTTPException(400, f"layers {layers!r}: name at least one of {level_layers(level)}")
    return resolve_layers(level, names)


def _check_window(
    level: Any, x: float, y: float, half_m: float, layers: list[str], limit: int
) -> None:
    """Refuse a non-finite centre or a window of more than ``limit`` values (cells x layers)."""
    if not (math.isfinite(x) and math.isfinite(y)):
        raise HTTPException(400, f"centre (x, y) = ({x}, {y}): values must be finite")
    if max(abs(x), abs(y)) > MAX_COORD_M:
        raise HTTPException(400, f"centre (x, y) = ({x}, {y}): beyond +-{MAX_COORD_M:g} m")
    if not (math.isfinite(half_m) and half_m > 0):
        raise HTTPException(400, f"half_m {half_m}: need a finite number > 0 (metres)")
    n = window_cells(level.resolution_m, x, y, min(half_m, 1e12))[2]
    if n * n * len(layers) > limit:
        raise HTTPException(
            413,
            f"window of half_m={half_m} m on level {level.name!r} "
            f"({level.resolution_m} m cells) is {n} x {n} cells x {len(layers)} layers = "
            f"{n * n * len(layers):,} values; at most {limit:,} in this format "
            f"(JSON {MAX_JSON_VALUES:,}, {NPY} or {ARROW_STREAM} {MAX_BINARY_VALUES:,})",
        )


# --- entities of attention ---------------------------------------------------------------------


def sp_level_of(key: str) -> int:
    """The SP level (1..5) ``key`` names: its number, or a map level's name (the SP level of
    the same number); HTTP 400 naming the key otherwise."""
    by_name = {name: n for n, name in MAP_LEVEL_NUMBERS.items()}
    if key in by_name:
        return by_name[key]
    if key.isascii() and key.isdecimal() and 1 <= int(key) <= 5:
        return int(key)
    raise HTTPException(400, f"level {key!r}: give an SP level 1..5 or one of {list(by_name)}")


def _track_sigmas(node: Any, t_ns: int) -> dict[int, float]:
    """SP's tracks that have a KD frame, with the standard deviation (m, world xy) of their
    position predicted to ``t_ns``: each opens a window on the next sweep."""
    sp = getattr(node, "sp", None)
    tracks = sp.tracker.tracks if sp is not None else ()
    if not len(tracks):
        return {}
    _, P = sp.tracker.predicted(t_ns)
    sig = np.sqrt(np.maximum(P[:, 0, 0] + P[:, 1, 1], 0.0))
    return {int(i): float(s) for i, s in zip(tracks.id, sig, strict=True) if i >= 0}


def _near_surprise(node: Any, xy: np.ndarray, size_m: np.ndarray) -> np.ndarray:
    """(N,) bool: a surprise point of last cycle lies within 1 m (SP's window base) plus the
    entity's half size ``size_m`` (N,) m of its position (world xy (N, 2) m)."""
    pts = node.attention_world_xyz
    if pts is None or not len(pts) or not len(xy):
        return np.zeros(len(xy), dtype=bool)
    d = np.linalg.norm(xy[:, None, :] - np.asarray(pts)[None, :, :2], axis=2).min(axis=1)
    return d <= 1.0 + size_m


def attention_entities(node: Any, sp_level: int, t_ns: int) -> list[dict]:
    """The entities of ``sp_level`` the node attends to, with why (module docstring), most
    urgent first (attention list rank, then id). Positions world m; call it between cycles."""
    kd = node.kd
    node_level = kd.config.memory.node_of_sp_level[sp_level]
    try:
        ranked = {int(i): r for r, i in enumerate(kd.attention(node_level))}
    except KeyError:
        ranked = {}
    sig = _track_sigmas(node, t_ns) if sp_level == 4 else {}
    frames = [
        f for f in kd.entities()
        if int(f.level) == sp_level and f.id != node.self_id and f.state is not None
        and f.state.frame == "world" and f.status.value not in ENDED
    ]  # fmt: skip
    xy = np.array([f.state.position_xyz[:2] for f in frames]).reshape(-1, 2)
    size = np.array([_half_size_m(f) for f in frames])
    surprised = _near_surprise(node, xy, size)
    out = []
    for f, near in zip(frames, surprised, strict=True):
        why = []
        if f.id in ranked:
            why.append(f"attention list of {node_level!r}, rank {ranked[f.id] + 1}")
        if f.id in sig:
            why.append(f"predicted window (position sigma {sig[f.id]:.2f} m)")
        if near:
            why.append("surprise window (last cycle's prediction missed near it)")
        if f.status.value == "hypothesized":
            why.append("hypothesis awaiting confirmation")
        if why:
            out.append(_attended(f, why, ranked.get(f.id)))
    return sorted(out, key=lambda e: (e["rank"] is None, e["rank"] or 0, e["entity_id"]))


def attention_copies(
    node: Any, wanted: Sequence[Hashable], cycle_t_ns: int
) -> dict[int, tuple[str, list[dict]]]:
    """SP level -> (its node level, :func:`attention_entities` as of ``cycle_t_ns``) for the
    levels among ``wanted`` (demand keys, :func:`wm.serve_copy.attention_key`), for the
    cycle's copy; call it under the node's lock, at the end of a cycle. A level that fails is
    logged and left out (its requests then read under the lock): the copy never stops the
    node."""
    out = {}
    for key in wanted:
        if not (isinstance(key, tuple) and key[0] == "attention"):
            continue
        sp_level = int(key[1])
        try:
            node_level = node.kd.config.memory.node_of_sp_level[sp_level]
            out[sp_level] = (node_level, attention_entities(node, sp_level, cycle_t_ns))
        except Exception:
            log.exception("attention of SP level %s at t_ns=%s: not copied", sp_level, cycle_t_ns)
    return out


def attention_now(live: Any, sp_level: int) -> tuple[int, str, list[dict]]:
    """(the newest cycle's time, the node level of SP level ``sp_level``, its
    :func:`attention_entities`), worked out under the node's lock between two cycles: the
    first request for a level (a :meth:`wm.serve.LiveNode.call`)."""
    with live.lock:
        node = running_node(live)
        snap = live.snapshot  # set under the lock with the cycle
        cycle = snap.cycle_t_ns if snap is not None else -1
        ents = attention_entities(node, sp_level, cycle)
        return cycle, node.kd.config.memory.node_of_sp_level[sp_level], ents


def _half_size_m(f: Any) -> float:
    """Half the larger of the entity's length and width (m), 0 when it has neither."""
    sizes = [0.0]
    for name in ("length_m", "width_m"):
        a = f.attributes.get(name)
        if a is not None:
            sizes += [v for v in (a.estimated, a.observed) if math.isfinite(v)]
    return 0.5 * max(sizes)


def _attended(f: Any, why: list[str], rank: int | None) -> dict:
    s = f.state
    return {
        "entity_id": int(f.id), "class_name": f.most_specific_class,
        "level": int(f.level), "status": f.status.value, "confidence": float(f.confidence),
        "t_ns": int(s.t_ns), "frame": s.frame, "position": _finite(s.position_xyz),
        "rank": None if rank is None else rank + 1, "why": why,
    }  # fmt: skip


def _finite(a: Any) -> list[float | None]:
    return [float(v) if math.isfinite(v) else None for v in np.asarray(a, np.float64).ravel()]


# --- the push stream ---------------------------------------------------------------------------


class StreamClient:
    """One stream reader's bounded queue of encoded cycles. The node's thread puts, the
    server's event loop takes; when full, a put drops the oldest cycle and counts it."""

    def __init__(self, max_cycles: int = STREAM_QUEUE_CYCLES) -> None:
        if max_cycles < 1:
            from wm.serve import ServeError

            raise ServeError(f"stream queue of {max_cycles} cycles: need at least 1")
        self.max_cycles = max_cycles
        self._queue: deque[bytes] = deque()
        self._lock = threading.Lock()
        self._unreported = 0  # dropped since the last message taken
        self.dropped = 0  # dropped in all

    def put(self, message: bytes) -> None:
        with self._lock:
            if len(self._queue) >= self.max_cycles:
                self._queue.popleft()  # the oldest: a reader that catches up wants the newest
                self._unreported += 1
                self.dropped += 1
            self._queue.append(message)

    def take(self) -> tuple[bytes, int] | None:
        """The oldest queued cycle and how many were dropped before it, or None."""
        with self._lock:
            if not self._queue:
                return None
            dropped, self._unreported = self._unreported, 0
            return self._queue.popleft(), dropped


def _stream_entity(c: dict[str, np.ndarray], k: int, why: str | None = None) -> dict:
    e = {
        "entity_id": int(c["id"][k]), "level": int(c["level"][k]),
        "class_name": c["class_name"][k], "status": c["status"][k],
        "confidence": float(c["confidence"][k]), "t_ns": int(c["t_ns"][k]),
        "frame": c["frame"][k], "position": _finite(c["position"][k]),
        "velocity": _finite(c["velocity"][k]),
    }  # fmt: skip
    return e if why is None else e | {"why": why}


class CycleFeed:
    """What each node cycle changed, pushed to every stream client (module docstring), in the
    server's process. The node makes one message per cycle (:class:`CycleDiff`, attached by
    the first subscription, making messages only while the stream has clients) and hands it
    to :meth:`distribute`: from its own thread, or from its process through the server's."""

    def __init__(self, live: Any, max_cycles: int = STREAM_QUEUE_CYCLES) -> None:
        self.live, self.max_cycles = live, max_cycles
        self._clients: set[StreamClient] = set()
        self._lock = threading.Lock()
        self._attached = False
        self.published = 0
        self.dropped_gone = 0  # dropped by clients that have left
        live.stream_sink = self.distribute

    def status(self) -> dict:
        with self._lock:
            clients = list(self._clients)
        dropped = self.dropped_gone + sum(c.dropped for c in clients)
        return {"clients": len(clients), "cycles": self.published, "dropped": dropped}

    def subscribe(self) -> StreamClient:
        """A new client's queue; the first one attaches the node's :class:`CycleDiff`
        (:class:`wm.serve.ServeError` when the node's process is gone)."""
        if not self._attached:
            self._attached = self.live.call(attach_stream)
        client = StreamClient(self.max_cycles)
        with self._lock:
            self._clients.add(client)
            self.live.tell_stream_clients(len(self._clients))
        return client

    def remove(self, client: StreamClient) -> None:
        from wm.serve import ServeError

        with self._lock:
            if client in self._clients:
                self._clients.discard(client)
                self.dropped_gone += client.dropped
                with contextlib.suppress(ServeError):  # a node gone has no one to tell
                    self.live.tell_stream_clients(len(self._clients))

    def distribute(self, message: bytes) -> None:
        """One cycle's message (:class:`CycleDiff`) to every client, numbered here."""
        with self._lock:
            clients = list(self._clients)
            if not clients:
                return
            self.published += 1
            number = self.published
        message = b'{"cycle":%d,' % number + message[1:]
        for c in clients:
            c.put(message)


def attach_stream(live: Any) -> bool:
    """Attach a :class:`CycleDiff` to the node once, between two cycles (its baseline is one
    cycle's columns); whether one is attached (False: the node is not running). A
    :meth:`wm.serve.LiveNode.call`."""
    with live.lock:
        if live.stream_diff is None and live.node is not None and not live.closed:
            diff = CycleDiff(live)
            diff.baseline()
            live.node.cycle_listeners.append(diff.on_cycle)
            live.stream_diff = diff
        return live.stream_diff is not None


class CycleDiff:
    """At the end of every node cycle, in the node's thread: what the cycle changed
    (entities created, changed, ended; events made) as one JSON message for the stream, to
    ``live.stream_sink`` while the stream has clients (``live.stream_clients``); with none,
    only the baseline is kept current."""

    def __init__(self, live: Any) -> None:
        self.live = live
        self._prev: dict[str, np.ndarray] | None = None  # columns after the last cycle
        self._next_id = 0  # the KD's next frame id after the last cycle

    def baseline(self) -> None:
        self._prev = self._sorted(self.live.kd.current_columns())
        self._next_id = int(self.live.kd.next_id)

    @staticmethod
    def _sorted(c: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        order = np.argsort(c["id"], kind="stable")
        return {k: v[order] for k, v in c.items()}

    def on_cycle(self, result: Any) -> None:
        """At the end of a cycle, in the node's thread: a fault here is logged, never raised,
        so a stream can not stop the node."""
        try:
            self._publish(int(result.t_ns))
        except Exception:
            log.exception("stream: the cycle at t_ns=%s was not published", result.t_ns)

    def _publish(self, t_ns: int) -> None:
        kd = self.live.kd
        now = self._sorted(kd.current_columns())
        prev, first_new = self._prev, self._next_id
        self._prev, self._next_id = now, int(kd.next_id)
        sink = self.live.stream_sink
        if not self.live.stream_clients or prev is None or sink is None:
            return  # nobody listens: keep only the baseline current
        created, changed, ended = _diff(prev, now)
        body = {
            "cycle_t_ns": t_ns, "frame": "world",
            "self_id": self.live.node.self_id,
            "created": [_stream_entity(now, k) for k in created],
            "changed": [_stream_entity(now, k) for k in changed],
            "ended": [_stream_entity(now, k, now["status"][k]) for k in ended[0]]
            + [_stream_entity(prev, k, "forgotten") for k in ended[1]],
            "events": _new_events(kd, first_new, self._next_id),
        }  # fmt: skip
        sink(json.dumps(body, separators=(",", ":")).encode())


def _diff(
    prev: dict[str, np.ndarray], now: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Rows of ``now`` created and changed since ``prev``, and ended: (rows of ``now`` newly
    denied or gone, rows of ``prev`` no longer held). Both sorted by id."""
    n_prev = len(prev["id"])
    pos = np.minimum(np.searchsorted(prev["id"], now["id"]), max(n_prev - 1, 0))
    known = prev["id"][pos] == now["id"] if n_prev else np.zeros(len(now["id"]), dtype=bool)
    p, k = pos[known], np.flatnonzero(known)
    moved = np.zeros(len(k), dtype=bool)
    for name in ("t_ns", "status", "class_name", "confidence"):  # a new state, or a new word
        moved |= prev[name][p] != now[name][k]
    now_ended = np.isin(now["status"][k], ENDED) & ~np.isin(prev["status"][p], ENDED)
    gone = ~np.isin(prev["id"], now["id"])
    return (
        np.flatnonzero(~known),
        k[moved & ~now_ended],
        (k[now_ended], np.flatnonzero(gone & ~np.isin(prev["status"], ENDED))),
    )


def _new_events(kd: Any, first_id: int, next_id: int) -> list[dict]:
    """The events among the frames made with ids in [first_id, next_id) (one id space)."""
    from kd_store.errors import KDError

    out = []
    for i in range(first_id, next_id):
        try:
            e = kd.get_event(i)
        except KDError:
            continue  # an entity, or an event already forgotten
        out.append({
            "event_id": int(e.id), "name": e.name, "class_name": e.class_name,
            "t_start_ns": int(e.t_start_ns), "level": int(e.level),
            "t_end_ns": None if e.t_end_ns is None else int(e.t_end_ns),
            "confidence": float(e.confidence),
        })  # fmt: skip
    return out


async def _sse(live: Any, feed: CycleFeed, client: StreamClient) -> AsyncIterator[bytes]:
    """The client's cycles as server-sent events until the replay ends or the client goes
    (the server cancels this generator then; ``finally`` removes the client)."""
    idle = 0.0
    try:
        yield b": one event per node cycle\n\n"
        while True:
            got = client.take()
            if got is not None:
                msg, dropped = got
                # splice the client's own count into the shared encoding: no re-encoding
                data = b'{"dropped":%d,' % dropped + msg[1:]
                yield b"event: cycle\ndata: " + data + b"\n\n"
                idle = 0.0
                continue
            if live.status.done or live.closed or not live.running:  # a node gone: no more
                end = {"cycles": live.status.cycles, "cycle_t_ns": live.status.cycle_t_ns}
                yield b"event: end\ndata: " + json.dumps(end).encode() + b"\n\n"
                return
            if idle >= STREAM_KEEPALIVE_S:  # a write finds out whether the client is gone
                yield b": keep-alive\n\n"
                idle = 0.0
            await asyncio.sleep(STREAM_POLL_S)
            idle += STREAM_POLL_S
    finally:
        feed.remove(client)


# --- the routes --------------------------------------------------------------------------------


def add_view_routes(app: FastAPI, live: Any, stream_queue: int = STREAM_QUEUE_CYCLES) -> CycleFeed:
    """Add ``/v1/maps/{level}``, ``/v1/attention`` and ``/v1/stream`` over ``live`` (a
    :class:`wm.serve.LiveNode`) to ``app``; returns the stream's feed (its ``status()`` goes
    into ``/v1/status``). ``stream_queue``: cycles a stream client may fall behind."""
    feed = CycleFeed(live, stream_queue)
    app.state.stream_feed = feed  # for a caller in the same process (and the tests)

    @app.get("/v1/maps/{level}")
    async def map_view(
        request: Request,
        level: str,
        x: float,
        y: float,
        half_m: Annotated[float, Query(description="half-width of the window, m")] = 10.0,
        layers: str = "elevation",
    ) -> Response:
        """The named layers (comma-separated; an earlier name such as ``z_m2`` stands for the
        current one, named in ``renamed_layers``) of map level ``level`` (name or 2..5) in the
        window of half-width ``half_m`` m around world (x, y) m: JSON, or ``.npy`` / Arrow by
        the Accept header (module docstring of wm.serve_views). From the cycle's copy when it
        holds the layers (:func:`read_level`)."""
        accept = request.headers.get("accept", "")
        binary = NPY if NPY in accept else ARROW_STREAM if ARROW_STREAM in accept else None
        renamed: dict[str, str] = {}

        limit = MAX_BINARY_VALUES if binary else MAX_JSON_VALUES

        def layers_of(lvl: Any) -> list[str]:
            names, got = _wanted_layers(lvl, layers)
            renamed.update(got)
            _check_window(lvl, x, y, half_m, names, limit)
            return names

        def window(src: LevelRead) -> tuple[MapWindow, int]:
            return map_window(src.level, x, y, half_m, src.layers), src.cycle_t_ns

        # from the cycle's copy on the event loop; what needs the node waits in a worker
        got = read_level_copy(live, level, layers_of, window)
        if got is None:
            got = (await run_in_threadpool(read_level_node, live, level, layers_of, window),)
        w, cycle = got[0]
        if binary == NPY:
            return _npy_response(w, cycle, renamed)
        if binary == ARROW_STREAM:
            return _arrow_response(w, cycle, renamed)
        body = _window_meta(w, cycle, renamed) | {
            "values": {k: _layer_json(v) for k, v in w.values.items()}
        }
        return Response(json.dumps(body), media_type="application/json",
                        headers=renamed_headers(renamed))  # fmt: skip

    @app.get("/v1/attention")
    def attention(level: str = "4") -> dict:
        """Entities of SP level ``level`` (1..5 or a map level's name) the node attends to,
        each with ``why`` (module docstring of wm.serve_views), world frame. From the cycle's
        copy once the level was asked for (the cycles after copy it while it is asked); the
        first request works it out under the node's lock."""
        sp_level = sp_level_of(level)
        live.demand.ask([attention_key(sp_level)])
        snap = live.snapshot  # one read: a cycle ending now replaces it whole
        running_node(live)
        if snap is not None and sp_level in snap.attention:
            node_level, ents = snap.attention[sp_level]
            cycle = snap.cycle_t_ns
        else:
            from wm.serve import ServeError

            try:
                cycle, node_level, ents = live.call(attention_now, sp_level)
            except ServeError as e:
                raise HTTPException(503, str(e)) from None
        return {"cycle_t_ns": cycle, "frame": "world", "level": sp_level,
                "node_level": node_level, "entities": ents}  # fmt: skip

    @app.get("/v1/stream")
    def stream() -> StreamingResponse:
        """Server-sent events: ``event: cycle`` per node cycle (entities created, changed,
        ended; events made; ``dropped`` cycles this client missed), ``event: end`` at the end
        of the replay."""
        from wm.serve import ServeError

        if live.closed or not live.running:
            raise HTTPException(503, "the live node is not running (not started, or stopped)")
        try:
            client = feed.subscribe()
        except ServeError as e:
            raise HTTPException(503, str(e)) from None
        headers = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
        return StreamingResponse(
            _sse(live, feed, client), media_type="text/event-stream", headers=headers
        )

    return feed
