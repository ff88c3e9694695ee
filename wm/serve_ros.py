"""Map and What If queries of the live node in the shapes of three ROS 2 services, for
controllers that already speak them (:mod:`wm.serve`): a ROS bridge maps the JSON one to one,
field names and nesting as in the ``.msg`` and ``.srv`` definitions.

    POST /v1/grid_map/get_grid_map           grid_map_msgs/srv/GetGridMap
    POST /v1/elevation_mapping/check_safety  elevation_map_msgs/srv/CheckSafety
    POST /v1/nav2/is_path_valid              nav2_msgs/srv/IsPathValid

``builtin_interfaces/Time`` is ``{"sec", "nanosec"}``, ``std_msgs/Header`` ``{"stamp",
"frame_id"}``, and so on. Positions are world metres: ``frame_id`` must be ``"world"`` (the
frame of ``/v1/maps``, of regions and of What If plans; an omitted one is world), any other is
a 400 naming it. Every answer says which cycle it is from (``cycle_t_ns``, int64 ns of log
time; a ROS header's ``stamp`` is that time) and its frame. Fields beyond the ROS definitions
(``level``, ``why``, ``cycle_t_ns`` and the like) are extensions a bridge may drop. Bad values
get a 4xx naming them, as on the other endpoints: a non-finite number, a coordinate beyond
:data:`wm.serve_views.MAX_COORD_M` or a list too long 422 (pydantic, with its location); an
unknown frame, layer, a polygon of fewer than 3 points or no area 400; an unknown map level
404 (400 for IsPathValid, as ``/v1/whatif``); too large a window or path 413.

**GetGridMap** (:func:`grid_map_of`): the ``layers`` asked (all of the level's when none, as
the ``.srv`` says) of one map level (``level``, extension, default ``subsystem``, the level
``/v1/whatif`` defaults to; ``/v1/maps`` has no default) around (``position_x``,
``position_y``). The cells are those of the ``/v1/maps`` window (:func:`wm.serve_views.
map_window`, here rectangular: ``2 ceil(length_x / (2 res)) + 1`` cells along x, likewise
along y, centred on the cell holding the position), so the answered ``info.length_x``,
``length_y`` and ``pose`` are the cells', not the request's (grid_map's own ``getSubmap`` also
answers the cells covering the request). A layer's earlier name (``z_m2``) is taken for its
current one, which the answer uses, naming the rename in ``renamed_layers`` (extension,
{earlier: current}) and the ``X-Map-Renamed-Layers`` header. Cells beyond the level's scrolling
window hold the
layer's empty value; NaN is JSON null, as in ``/v1/maps``. Values are the layer's own, as
JSON numbers: a bridge filling ``Float32MultiArray`` rounds the int64 layers (``entity_id``,
``last_seen_ns``) beyond 2^24. At most :data:`wm.serve_views.MAX_JSON_VALUES` values.

The layout is grid_map's (grid_map_core ``getPositionFromIndex``; grid_map_ros
``GridMapRosConverter::toMessage`` and ``matrixEigenCopyToMultiArrayMessage``). A layer is a
column-major (Eigen's default) matrix M of ``size_x`` rows by ``size_y`` columns; index (0, 0)
is the cell of largest x and largest y, the row index grows towards -x and the column index
towards -y: M[i, j]'s centre is ``pose.position + (length_x/2 - res/2 - i res, length_y/2 -
res/2 - j res)``. ``layout.dim`` is ``[("column_index", size_y, size_x size_y), ("row_index",
size_x, size_x)]`` (label, size, stride) and ``data[j size_x + i] = M[i, j]``. With the
``/v1/maps`` window W (``ny`` rows from south to north, ``nx`` columns from west to east)
``M[i, j] = W[ny-1-j, nx-1-i]``: ``data`` is W turned by 180 degrees, read row by row.
``outer_start_index`` and ``inner_start_index`` are 0 (no circular buffer), ``basic_layers``
empty, ``info.pose`` the window centre with identity orientation.

**CheckSafety** (:func:`polygon_safety`): per polygon, over the cells of ``level`` whose
centres it holds (the one nearest its centroid when it holds none), ``is_safe`` is false when
a known cell is impassable (traversability 0: slope, step, roughness or occupancy at its
``maps.terrain.TerrainConfig`` limit, the rule What If and value judgment call blocked), when
an entity What If would collide with (object level, confirmed or hypothesized, not the
vehicle; its box as of the cycle) overlaps the polygon, or when no cell of it is known (as
elevation_mapping calls a polygon outside its map unsafe); other unknown cells are left out.
``traversability`` is the mean over the known cells (0 impassable .. 1 easy, as the ``.srv``
documents it; null when none is known). ``untraversable_polygons`` has one polygon per
request polygon, world frame, at the request's first point's z (as elevation_mapping sets
it): with ``compute_untraversable_polygon`` the convex hull of the impassable cells and the
overlapping entities' boxes, else (or with nothing untraversable) no points. Extensions:
``why`` and ``known_fraction`` (of its cells) per polygon. Polygons need 3 to
:data:`MAX_POLYGON_POINTS` points and an area; at most :data:`MAX_POLYGONS`, and at most
:data:`wm.serve_views.MAX_BINARY_VALUES` cells in their bounding boxes together (413). The
traversability and the entities' boxes come from the newest cycle's copy
(:class:`wm.serve.CycleSnapshot`: What If copies both each cycle), so CheckSafety takes no
lock and a large request holds up neither the node's cycle nor other requests; only for a
level What If does not serve (not in ``whatif.steps_s``) is each polygon's cells copied under
the node's lock (:func:`polygon_window`), until the cycles after copy its traversability.

GetGridMap and CheckSafety read the level as ``/v1/maps`` does
(:func:`wm.serve_views.read_level`): from the cycle's copy when it holds the layers, else
under the node's lock, copying only the window's cells.

**IsPathValid** (:func:`judge_path`): What If rolls the path out as a waypoint plan from the
vehicle's present state; the answer gives that ``plan`` with ``horizon_s`` and ``level``, and
``POST /v1/whatif`` makes the same rollout of them. As Nav2 does, the poses before the one
closest to the vehicle are passed, not judged, and with ``max_lookahead_distance`` > 0 only
the poses within that distance along the path from it. Timing: when the poses' stamps differ
they are the schedule (s after the closest pose's; they must increase along the path), else
the poses are taken along the path at the vehicle's present speed (:func:`path_speed`), at
least the planner's slowest forward speed and at most the vehicle model's top speed. The
rollout runs to the last pose's time plus the time the vehicle model needs to stop from the
path's top speed, at least one step. Each step gets a cost on Nav2's scale: 254 (lethal) where
the footprint meets an impassable cell (What If's blocked) or at the rollout's first
collision with an entity, else ``round(252 (1 - traversability))`` over the footprint's known
samples (0 when none is known). A step is invalid when lethal, when its cost is at least
``max_cost``, or when a footprint sample is unknown and ``consider_unknown_as_obstacle``
(Nav2's unknown, 255, counts as lethal then; else unknown cells are left out, where Nav2 calls
the whole pose free). An invalid step makes invalid the pose nearest the rollout there among
those due by then (the one being driven to and those before). ``stop_at_first_collision``
(default) lists the first invalid pose only, else every one (What If reports an entity
collision only where it first happens). ``success`` is true on every answer: a request that
cannot be judged is a 4xx. ``layer_name`` and ``footprint`` must be empty (the judgment is
What If's with its vehicle footprint); orientations are not used (the rollout's yaw is the
vehicle model's). Extensions: ``why`` (the blocking cell or entity, in the words of
``/v1/whatif``), ``collision_entity``, ``first_pose_index`` and ``end_pose_index`` (the poses
judged, ``[first, end)``), ``end_gap_m`` (from where the rollout ends to the last pose
judged: a large gap says the vehicle model did not follow the path, e.g. one behind it, where
it stops rather than reverse, and the poses it did not reach were not judged). At most
:data:`MAX_PATH_POSES` poses and a rollout of :data:`MAX_HORIZON_S` (413 beyond). The rollout
reads the newest cycle's copy (:class:`wm.serve.CycleSnapshot`), as ``/v1/whatif`` does, so
it never takes the node's lock.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

import numpy as np
from fastapi import FastAPI, HTTPException, Response
from pydantic import BaseModel, Field

from core.geometry import box_corners
from wm.config import PlannerConfig, VehicleConfig
from wm.serve import Finite, _why
from wm.serve_views import (
    MAX_BINARY_VALUES,
    MAX_COORD_M,
    MAX_JSON_VALUES,
    LevelRead,
    MapWindow,
    level_layers,
    map_window,
    read_level,
    renamed_headers,
    resolve_layers,
    window_span,
)

#: the only frame positions are taken and given in
WORLD = "world"
DEFAULT_LEVEL = "subsystem"  # as /v1/whatif
MAX_PATH_POSES = 10_000
MAX_POLYGONS = 100
MAX_POLYGON_POINTS = 100
MAX_HORIZON_S = 600.0  # the longest What If rollout /v1/whatif takes
#: m/s: the slowest an unscheduled path is driven (the planner's slowest forward speed)
MIN_PATH_SPEED_MPS = min(v for v in PlannerConfig().speeds_mps if v > 0)
LETHAL, MAX_PASSABLE = 254, 252  # Nav2's costmap values: lethal, highest passable
NS_PER_S = 1_000_000_000
#: a world coordinate, m: finite and within :data:`wm.serve_views.MAX_COORD_M` (422 beyond)
Coord = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_COORD_M, le=MAX_COORD_M)]


# --- ROS 2 messages (field names as in their .msg definitions) --------------------------------


class Time(BaseModel):
    """builtin_interfaces/Time: ``sec`` (int32) and ``nanosec`` (uint32, < 1e9)."""

    sec: int = Field(0, ge=-(2**31), le=2**31 - 1)
    nanosec: int = Field(0, ge=0, le=NS_PER_S - 1)


class Header(BaseModel):
    """std_msgs/Header; ``frame_id`` must be ``world`` (omitted: world)."""

    stamp: Time = Field(default_factory=Time)
    frame_id: str = Field(WORLD, max_length=200)


class Point(BaseModel):
    """geometry_msgs/Point, m."""

    x: Coord = 0.0
    y: Coord = 0.0
    z: Coord = 0.0


class Point32(Point):
    """geometry_msgs/Point32, m (float32 in ROS)."""


class Quaternion(BaseModel):
    """geometry_msgs/Quaternion (x, y, z, w)."""

    x: Finite = 0.0
    y: Finite = 0.0
    z: Finite = 0.0
    w: Finite = 1.0


class Pose(BaseModel):
    """geometry_msgs/Pose."""

    position: Point = Field(default_factory=Point)
    orientation: Quaternion = Field(default_factory=Quaternion)


class PoseStamped(BaseModel):
    """geometry_msgs/PoseStamped."""

    header: Header = Field(default_factory=Header)
    pose: Pose = Field(default_factory=Pose)


class Path(BaseModel):
    """nav_msgs/Path: at least one pose, at most :data:`MAX_PATH_POSES`."""

    header: Header = Field(default_factory=Header)
    poses: list[PoseStamped] = Field(..., min_length=1, max_length=MAX_PATH_POSES)


class Polygon(BaseModel):
    """geometry_msgs/Polygon."""

    points: list[Point32] = Field(default_factory=list, max_length=MAX_POLYGON_POINTS)


class PolygonStamped(BaseModel):
    """geometry_msgs/PolygonStamped."""

    header: Header = Field(default_factory=Header)
    polygon: Polygon = Field(default_factory=Polygon)


class MultiArrayDimension(BaseModel):
    """std_msgs/MultiArrayDimension."""

    label: str
    size: int
    stride: int


class MultiArrayLayout(BaseModel):
    """std_msgs/MultiArrayLayout."""

    dim: list[MultiArrayDimension]
    data_offset: int


class Float32MultiArray(BaseModel):
    """std_msgs/Float32MultiArray; NaN as null."""

    layout: MultiArrayLayout
    data: list[float | None]


class GridMapInfo(BaseModel):
    """grid_map_msgs/GridMapInfo: resolution m/cell, lengths m, pose of the map's centre."""

    resolution: float
    length_x: float
    length_y: float
    pose: Pose


class GridMap(BaseModel):
    """grid_map_msgs/GridMap (ROS 2): one Float32MultiArray per layer, column-major."""

    header: Header
    info: GridMapInfo
    layers: list[str]
    basic_layers: list[str]
    data: list[Float32MultiArray]
    outer_start_index: int
    inner_start_index: int


# --- requests and answers ----------------------------------------------------------------------


class GetGridMapRequest(BaseModel):
    """grid_map_msgs/srv/GetGridMap's request; ``level`` is an extension."""

    frame_id: str = Field(WORLD, max_length=200)
    position_x: Coord
    position_y: Coord
    length_x: Finite = Field(..., gt=0)
    length_y: Finite = Field(..., gt=0)
    layers: list[Annotated[str, Field(max_length=200)]] = Field(
        default_factory=list, max_length=100
    )
    level: str = Field(DEFAULT_LEVEL, max_length=200)


class GetGridMapAnswer(BaseModel):
    """GetGridMap's response (``map``) and where it is from (extensions); ``renamed_layers``
    (extension): the layers asked by an earlier name, {earlier: current}, answered under the
    current one."""

    map: GridMap
    cycle_t_ns: int
    frame: str
    level: str
    renamed_layers: dict[str, str] = Field(default_factory=dict)


class CheckSafetyRequest(BaseModel):
    """elevation_map_msgs/srv/CheckSafety's request; ``level`` is an extension."""

    polygons: list[PolygonStamped] = Field(..., max_length=MAX_POLYGONS)
    compute_untraversable_polygon: bool = False
    level: str = Field(DEFAULT_LEVEL, max_length=200)


class CheckSafetyAnswer(BaseModel):
    """CheckSafety's response, one entry per polygon; ``why``, ``known_fraction``,
    ``cycle_t_ns``, ``frame`` and ``level`` are extensions."""

    is_safe: list[bool]
    traversability: list[float | None]
    untraversable_polygons: list[PolygonStamped]
    why: list[str]
    known_fraction: list[float]
    cycle_t_ns: int
    frame: str
    level: str


class IsPathValidRequest(BaseModel):
    """nav2_msgs/srv/IsPathValid's request (the current definition, its defaults); ``level``
    is an extension."""

    path: Path
    max_cost: int = Field(LETHAL, ge=0, le=255)
    consider_unknown_as_obstacle: bool = False
    layer_name: str = Field("", max_length=200)
    footprint: str = Field("", max_length=2000)
    stop_at_first_collision: bool = True
    max_lookahead_distance: Finite = -1.0
    level: str = Field(DEFAULT_LEVEL, max_length=200)


class PlanJSON(BaseModel):
    """The waypoint plan rolled out, as ``POST /v1/whatif`` takes it."""

    name: str
    t_s: list[float]
    xy: list[list[float]]


class IsPathValidAnswer(BaseModel):
    """IsPathValid's response; the fields after ``invalid_pose_indices`` are extensions."""

    success: bool
    is_valid: bool
    invalid_pose_indices: list[int]
    why: str
    collision_entity: int | None
    first_pose_index: int
    end_pose_index: int
    end_gap_m: float
    plan: PlanJSON
    horizon_s: float
    cycle_t_ns: int
    frame: str
    level: str


# --- shared ------------------------------------------------------------------------------------


def stamp_of(t_ns: int) -> dict:
    """builtin_interfaces/Time of int64 ns (floor: a negative time keeps nanosec >= 0)."""
    return {"sec": t_ns // NS_PER_S, "nanosec": t_ns % NS_PER_S}


def header_of(t_ns: int) -> dict:
    return {"stamp": stamp_of(t_ns), "frame_id": WORLD}


def check_frame(frame_id: str, where: str) -> None:
    """HTTP 400 unless ``frame_id`` is the world frame."""
    if frame_id != WORLD:
        raise HTTPException(
            400,
            f"{where} frame_id {frame_id!r}: unknown; positions are taken and given in "
            f"{WORLD!r} only (the frame of /v1/maps, /v1/entities and /v1/whatif)",
        )


def _nulled(a: np.ndarray) -> list[float | None]:
    """Values as float, NaN and infinities as null (as the JSON map windows give them)."""
    f = np.asarray(a, dtype=np.float64)
    obj = f.astype(object)
    obj[~np.isfinite(f)] = None
    return obj.tolist()


# --- GetGridMap --------------------------------------------------------------------------------


def grid_map_of(w: MapWindow, cycle_t_ns: int) -> dict:
    """A /v1/maps window as grid_map_msgs/GridMap (module docstring: index (0, 0) at the cell
    of largest x and y, rows along -x, columns along -y, column-major data)."""
    ny, nx = w.shape
    res = w.resolution_m
    ox, oy = w.origin_xy
    layout = {
        "dim": [
            {"label": "column_index", "size": ny, "stride": nx * ny},
            {"label": "row_index", "size": nx, "stride": nx},
        ],
        "data_offset": 0,
    }
    # data[j nx + i] = M[i, j] = W[ny-1-j, nx-1-i]: W turned by 180 degrees, row by row
    data = [{"layout": layout, "data": _nulled(v[::-1, ::-1].ravel())} for v in w.values.values()]
    centre = {"x": ox + 0.5 * nx * res, "y": oy + 0.5 * ny * res, "z": 0.0}
    return {
        "header": header_of(cycle_t_ns),
        "info": {
            "resolution": res, "length_x": nx * res, "length_y": ny * res,
            "pose": {"position": centre, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
        },
        "layers": list(w.values), "basic_layers": [], "data": data,
        "outer_start_index": 0, "inner_start_index": 0,
    }  # fmt: skip


def _grid_layers(level: Any, names: list[str]) -> tuple[list[str], dict[str, str]]:
    """The layers asked (all of the level's when none), each once, an earlier name standing
    for its current one (:func:`wm.serve_views.resolve_layers`: 400 naming unknown ones)."""
    return resolve_layers(level, names) if names else (level_layers(level), {})


def _check_grid_window(level: Any, req: GetGridMapRequest, layers: list[str]) -> None:
    """413 for a window of more than :data:`MAX_JSON_VALUES` values (cells x layers)."""
    res = level.resolution_m
    nx = window_span(res, req.position_x, min(0.5 * req.length_x, 1e12))[1]
    ny = window_span(res, req.position_y, min(0.5 * req.length_y, 1e12))[1]
    values = nx * ny * len(layers)
    if values > MAX_JSON_VALUES:
        raise HTTPException(
            413,
            f"grid map of length_x={req.length_x} m, length_y={req.length_y} m on level "
            f"{level.name!r} ({res} m cells) is {nx} x {ny} cells x {len(layers)} layers = "
            f"{values:,} values; at most {MAX_JSON_VALUES:,} (ask fewer layers or a smaller map)",
        )


# --- CheckSafety -------------------------------------------------------------------------------


def polygon_area(poly: np.ndarray) -> float:
    """Area (m^2) of a simple polygon (K, 2), shoelace formula."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _segments_cross(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> bool:
    """Whether any segment a0[i]-a1[i] properly crosses any b0[j]-b1[j] (all (n, 2))."""

    def side(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (
            r[..., 0] - p[..., 0]
        )

    A0, A1, B0, B1 = a0[:, None], a1[:, None], b0[None], b1[None]
    d1, d2 = side(B0, B1, A0), side(B0, B1, A1)
    d3, d4 = side(A0, A1, B0), side(A0, A1, B1)
    return bool(np.any((d1 * d2 < 0) & (d3 * d4 < 0)))


def _inside_points(xy: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(N,) bool: which of a few points ``xy`` (N, 2) lie inside the simple polygon ``poly``
    (K, 2): :func:`maps.submap.inside_polygon`'s even-odd rule and arithmetic, all edges at
    once ((N, K) arrays, so for small N: a box's corners, a polygon's points)."""
    x0, y0 = poly[:, 0], poly[:, 1]
    nxt = np.roll(poly, -1, axis=0)
    x1, y1 = nxt[:, 0], nxt[:, 1]
    x, y = xy[:, 0, None], xy[:, 1, None]
    straddles = (y0 > y) != (y1 > y)  # never for a horizontal edge: its division is unused
    with np.errstate(divide="ignore", invalid="ignore"):
        crosses = straddles & (x < x0 + (y - y0) * (x1 - x0) / (y1 - y0))
    return np.logical_xor.reduce(crosses, axis=1)


def _inside_grid(xc: np.ndarray, yr: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(ny, nx) bool: which centres of the grid of columns at x ``xc`` (nx,, increasing) and
    rows at y ``yr`` (ny,) lie inside the simple polygon ``poly`` (K, 2). The even-odd rule
    of :func:`maps.submap.inside_polygon` with its arithmetic, so the same cells: a ray from
    (x, y) towards +x crosses an edge that straddles the row where ``x < x_cross``; the
    crossings are worked out once per row and edge (ny x K), and a cell's count is how many
    of its row's crossings lie beyond its column (a reverse cumulative sum over columns),
    instead of testing every cell against every edge."""
    x0, y0 = poly[:, 0], poly[:, 1]
    nxt = np.roll(poly, -1, axis=0)
    x1, y1 = nxt[:, 0], nxt[:, 1]
    y = yr[:, None]
    straddles = (y0 > y) != (y1 > y)  # (ny, K); never for a horizontal edge
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    r, e = np.nonzero(straddles)
    # the columns whose centre is left of the crossing: xc[c] < x_cross <=> c < first
    first = np.searchsorted(xc, x_cross[r, e], side="left")
    nx = len(xc)
    ends = np.bincount(r * (nx + 1) + first, minlength=len(yr) * (nx + 1))
    beyond = np.cumsum(ends.reshape(len(yr), nx + 1)[:, ::-1], axis=1)[:, ::-1]
    return (beyond[:, 1:] & 1).astype(bool)


def box_overlaps_polygon(corners: np.ndarray, poly: np.ndarray) -> bool:
    """Whether a convex box (4, 2) and a simple polygon (K, 2) overlap: a corner of one lies
    inside the other, or their edges cross."""
    if _inside_points(corners, poly).any() or _inside_points(poly, corners).any():
        return True
    return _segments_cross(corners, np.roll(corners, -1, 0), poly, np.roll(poly, -1, 0))


def convex_hull(pts: np.ndarray) -> np.ndarray:
    """(H, 2) convex hull of points (N, 2) world m, counter-clockwise: OpenCV picks the
    points (in float32, about their mean, so it decides right far from the origin); the
    hull is made of the input points themselves."""
    import cv2

    rel = (pts - pts.mean(axis=0)).astype(np.float32)
    idx = cv2.convexHull(rel, clockwise=False, returnPoints=False).reshape(-1)
    return pts[idx].astype(np.float64)


def polygon_window(level: Any, poly: np.ndarray) -> MapWindow:
    """The traversability of the level's cells in the bounding box of ``poly`` (K, 2) world
    m: a copy (:func:`wm.serve_views.map_window`), so that the verdict can be worked out
    without the level (from the cycle's copy, or after the node's lock is released)."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    c, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    return map_window(level, c[0], c[1], half[0], ["traversability"], half_y_m=half[1])


def polygon_cells(w: MapWindow, poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Traversability (N,) and cell-centre world xy (N, 2) m of the cells of ``w``
    (:func:`polygon_window`) whose centres ``poly`` holds (the cell nearest its vertices'
    mean when it holds none), in row-major order (rows south to north)."""
    ny, nx = w.shape
    res = w.resolution_m
    xc = w.origin_xy[0] + (np.arange(nx) + 0.5) * res
    yr = w.origin_xy[1] + (np.arange(ny) + 0.5) * res
    trav = w.values["traversability"].astype(np.float64).ravel()
    inside = _inside_grid(xc, yr, poly).ravel()
    if not inside.any():
        xy = np.stack(np.broadcast_arrays(xc[None, :], yr[:, None]), axis=-1).reshape(-1, 2)
        inside[np.argmin(np.linalg.norm(xy - poly.mean(axis=0), axis=1))] = True
    rows, cols = np.divmod(np.flatnonzero(inside), nx)
    return trav[inside], np.stack([xc[cols], yr[rows]], axis=1)


def overlapping_boxes(boxes: Any, poly: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """(entity id, footprint corners (4, 2)) of the boxes (:class:`wm.shapes.EntityBoxes`,
    world frame) that overlap the polygon (K, 2)."""
    out = []
    # a box more than a millimetre beside the polygon's bounding box cannot overlap it (the
    # margin keeps the float rounding of the exact tests below far from mattering)
    lo, hi = poly.min(axis=0) - 1e-3, poly.max(axis=0) + 1e-3
    for k in range(len(boxes)):
        corners = box_corners(boxes.centers_xyz[k], *boxes.sizes_lwh[k, :2], boxes.yaws[k])
        if np.any(corners.max(axis=0) < lo) or np.any(corners.min(axis=0) > hi):
            continue
        if box_overlaps_polygon(corners, poly):
            out.append((int(boxes.ids[k]), corners))
    return out


def _safety_why(hits: list, trav: np.ndarray, xy: np.ndarray) -> str:
    """Why a polygon is (un)safe: an overlapping entity, a blocked cell, no known cell, or
    clear with its least traversability."""
    known = np.isfinite(trav)
    blocked = np.flatnonzero(known & (trav <= 0.0))
    if hits:
        i, corners = hits[0]
        cx, cy = corners.mean(axis=0)
        if len(hits) == 1:
            return f"entity {i} at ({cx:.1f}, {cy:.1f}) m overlaps the polygon"
        ids = ", ".join(str(h[0]) for h in hits)
        return f"entities {ids} overlap the polygon ({i} at ({cx:.1f}, {cy:.1f}) m)"
    if blocked.size:
        x, y = xy[blocked[0]]
        return f"blocked cell at ({x:.1f}, {y:.1f}) m (traversability 0)"
    if not known.any():
        return f"no known cell among its {len(trav)}: not judged safe"
    least = float(trav[known].min())
    return f"clear: least traversability {least:.2f} over {int(known.sum())} known cells"


def _untraversable_points(hits: list, blocked_xy: np.ndarray, res: float, z: float) -> list:
    """Points (geometry_msgs/Point32) of the convex hull of the blocked cells' corners (cell
    centres ``blocked_xy`` (B, 2), cells ``res`` m) and the overlapping entities' boxes."""
    square = 0.5 * res * np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]])
    pts = [(blocked_xy[:, None, :] + square).reshape(-1, 2), *[c for _, c in hits]]
    hull = convex_hull(np.concatenate(pts)) if blocked_xy.size or hits else np.zeros((0, 2))
    return [{"x": float(x), "y": float(y), "z": z} for x, y in hull]


def polygon_safety(
    w: MapWindow, boxes: Any, poly: np.ndarray, z: float, hull: bool, cycle_t_ns: int
) -> dict:
    """One polygon's CheckSafety verdict (module docstring): ``is_safe``, ``traversability``,
    ``untraversable_polygon`` (PolygonStamped, its points at height ``z`` m when ``hull``),
    ``why``, ``known_fraction``. ``w``: the polygon's :func:`polygon_window`; ``boxes``: the
    entities' boxes (:class:`wm.shapes.EntityBoxes`) as of the cycle, world frame. Reads
    neither the node nor its maps, so it runs outside the node's lock."""
    trav, xy = polygon_cells(w, poly)
    known = np.isfinite(trav)
    blocked = known & (trav <= 0.0)
    hits = overlapping_boxes(boxes, poly)
    points = _untraversable_points(hits, xy[blocked], w.resolution_m, z) if hull else []
    return {
        "is_safe": bool(known.any() and not blocked.any() and not hits),
        "traversability": float(trav[known].mean()) if known.any() else None,
        "untraversable_polygon": {"header": header_of(cycle_t_ns), "polygon": {"points": points}},
        "why": _safety_why(hits, trav, xy),
        "known_fraction": float(known.mean()),
    }


def _polygon_xy(p: PolygonStamped, k: int) -> np.ndarray:
    """Polygon ``k``'s points (K, 2) world m; 400 naming it when it has fewer than three
    points or no area, or is not in the world frame."""
    check_frame(p.header.frame_id, f"polygon {k}:")
    pts = np.array([[q.x, q.y] for q in p.polygon.points], dtype=np.float64).reshape(-1, 2)
    if len(pts) < 3:
        raise HTTPException(400, f"polygon {k} has {len(pts)} points: need at least 3")
    if polygon_area(pts) <= 0.0:
        raise HTTPException(400, f"polygon {k} {pts.tolist()[:4]}: its points enclose no area")
    return pts


def _check_polygon_cells(level: Any, polys: list[np.ndarray]) -> None:
    """413 when the polygons' bounding boxes hold more than :data:`MAX_BINARY_VALUES` cells."""
    res, total = level.resolution_m, 0
    for k, poly in enumerate(polys):
        lo, hi = poly.min(axis=0), poly.max(axis=0)
        c, half = 0.5 * (lo + hi), np.minimum(0.5 * (hi - lo), 1e12)
        cells = window_span(res, c[0], half[0])[1] * window_span(res, c[1], half[1])[1]
        total += cells
        if total > MAX_BINARY_VALUES:
            raise HTTPException(
                413,
                f"polygon {k} spans {hi[0] - lo[0]:.6g} x {hi[1] - lo[1]:.6g} m: the polygons "
                f"cover {total:,} cells of level {level.name!r} ({res} m) so far; at most "
                f"{MAX_BINARY_VALUES:,}",
            )


def node_what_if(node: Any) -> Any:
    """What If over the node's own KD and maps with the server's configuration
    (:func:`wm.serve.served_config`); use it under the node's lock."""
    from wm.whatif import WhatIf

    return WhatIf(node.kd, node.stack, node.engine_config, self_id=node.self_id)


def source_what_if(src: LevelRead) -> Any:
    """What If over what ``src`` reads: the cycle's copy, or the node under its lock."""
    if src.snapshot is not None:
        from wm.serve import what_if_over

        return what_if_over(src.snapshot)
    return node_what_if(src.node)


def _entity_boxes(wi: Any, polys: list[np.ndarray], cycle_t_ns: int) -> Any:
    """The boxes of the entities What If ``wi`` would collide with, near the polygons, as of
    the cycle (world frame); its configuration's search margin."""
    from wm.shapes import boxes_of

    if cycle_t_ns < 0 or not polys:  # no cycle yet: the KD holds no entity
        return boxes_of([])
    pts = np.concatenate(polys)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    reach = 0.5 * float(np.linalg.norm(hi - lo)) + wi.config.entity_search_margin_m
    return wi.entities_near(0.5 * (lo + hi), reach, cycle_t_ns)


# --- IsPathValid -------------------------------------------------------------------------------


def _path_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 2) world m and stamps (N,) int64 ns of the path's poses; 400 naming a
    pose not in the world frame."""
    check_frame(path.header.frame_id, "path:")
    for k, p in enumerate(path.poses):
        check_frame(p.header.frame_id, f"pose {k}:")
    xy = np.array([[p.pose.position.x, p.pose.position.y] for p in path.poses], np.float64)
    t = np.array([p.header.stamp.sec * NS_PER_S + p.header.stamp.nanosec for p in path.poses])
    return xy, t.astype(np.int64)


def path_speed(present_mps: float, veh: VehicleConfig) -> float:
    """The speed (m/s) an unscheduled path is driven at: the vehicle's present speed, so the
    rollout goes on as the vehicle moves (a controller's path starts where it drives), within
    :data:`MIN_PATH_SPEED_MPS` and the vehicle model's top speed."""
    return float(np.clip(present_mps, MIN_PATH_SPEED_MPS, veh.max_speed_mps))


def path_schedule(
    xy: np.ndarray, stamps_ns: np.ndarray, first: int, end: int, speed_mps: float
) -> np.ndarray:
    """Times (s, from pose ``first``) of poses ``first .. end-1``: their stamps when the path's
    stamps differ (400 naming the first that does not increase), else along the path at
    ``speed_mps``."""
    if np.any(stamps_ns != stamps_ns[0]):
        bad = np.flatnonzero(np.diff(stamps_ns) <= 0)
        if bad.size:
            k = int(bad[0])
            raise HTTPException(
                400,
                f"pose {k + 1} stamp {int(stamps_ns[k + 1])} ns is not after pose {k}'s "
                f"{int(stamps_ns[k])} ns: stamps, when they differ, must increase along the path",
            )
        return (stamps_ns[first:end] - stamps_ns[first]) / NS_PER_S
    seg = np.linalg.norm(np.diff(xy[first:end], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)]) / speed_mps


def judged_span(xy: np.ndarray, start_xy: np.ndarray, lookahead_m: float) -> tuple[int, int]:
    """``[first, end)``: poses from the one closest to the vehicle on, within ``lookahead_m``
    along the path when that is > 0 (Nav2's IsPathValid service)."""
    first = int(np.argmin(np.linalg.norm(xy - start_xy[:2], axis=1)))
    if lookahead_m <= 0:
        return first, len(xy)
    along = np.cumsum(np.linalg.norm(np.diff(xy[first:], axis=0), axis=1))
    beyond = np.flatnonzero(along > lookahead_m)
    return first, first + 1 + int(beyond[0]) if beyond.size else len(xy)


def _waypoints(xy: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plan's waypoints: poses whose time is after the one before (a repeated pose at
    the default speed, or a repeated stamp, is one waypoint)."""
    keep = np.concatenate([[True], np.diff(t_s) > 0])
    return t_s[keep], xy[keep]


def plan_horizon_s(t_s: np.ndarray, xy: np.ndarray, dt: float, veh: VehicleConfig) -> float:
    """The rollout's horizon (s): the last waypoint's time plus the time the vehicle model
    needs to stop from the plan's top speed, at least one step ``dt`` (an unknown level's
    NaN step is left to What If to refuse); 413 beyond :data:`MAX_HORIZON_S`."""
    speeds = np.linalg.norm(np.diff(xy, axis=0), axis=1) / np.diff(t_s) if len(t_s) > 1 else [0]
    stop_s = float(np.max(speeds, initial=0.0)) / veh.max_decel_mps2
    horizon = float(t_s[-1]) + (max(stop_s, dt) if math.isfinite(dt) else stop_s)
    if horizon > MAX_HORIZON_S:
        raise HTTPException(
            413,
            f"path of {len(t_s)} waypoints takes {horizon:.6g} s to roll out; at most "
            f"{MAX_HORIZON_S:g} s (the What If horizon limit)",
        )
    return max(horizon, 1e-3)


def step_costs(result: Any, collision_step: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Per rollout step (S+1,): the cost on Nav2's scale of the footprint's known samples
    (module docstring; 0 when none is known) and whether any sample is unknown."""
    trav = result.traversability[0]  # the footprint's least, NaN when none is known
    cost = np.rint(MAX_PASSABLE * (1.0 - np.nan_to_num(trav, nan=1.0))).astype(np.int64)
    cost[np.nan_to_num(trav, nan=1.0) <= 0.0] = LETHAL  # What If's blocked cell
    if collision_step is not None:
        cost[collision_step] = LETHAL
    return cost, result.unknown_fraction[0] > 0


def pose_of_step(result: Any, s: int, xy: np.ndarray, t_pose: np.ndarray, first: int) -> int:
    """The path index of the pose rollout step ``s`` makes invalid: the nearest to the
    rollout there among poses ``first ..`` due up to the step's time (the one being driven to
    included)."""
    due = int(np.searchsorted(t_pose, result.t_s[s] - 1e-9))  # first pose due at or after it
    k_end = min(due, len(t_pose) - 1) + 1
    d = np.linalg.norm(xy[first : first + k_end] - result.xy[0, s], axis=1)
    return first + int(np.argmin(d))


def judge_path(
    req: IsPathValidRequest, result: Any, xy: np.ndarray, t_pose: np.ndarray, first: int
) -> dict:
    """IsPathValid's verdict over a rollout of the path (module docstring): ``is_valid``,
    ``invalid_pose_indices``, ``why``, ``collision_entity``."""
    collided = int(result.collision_entity[0]) >= 0
    s_hit = int(np.argmin(np.abs(result.t_s - result.collision_t_s[0]))) if collided else None
    cost, unknown = step_costs(result, s_hit)
    invalid = (cost >= LETHAL) | (cost >= req.max_cost)
    invalid |= unknown & req.consider_unknown_as_obstacle  # Nav2: unknown (255) as lethal
    steps = np.flatnonzero(invalid)
    if req.stop_at_first_collision:
        steps = steps[:1]
    poses = sorted({pose_of_step(result, int(s), xy, t_pose, first) for s in steps})
    why = _why(result, 0) if not steps.size else _step_why(result, int(steps[0]), s_hit, cost, req)
    return {
        "is_valid": not poses, "invalid_pose_indices": poses, "why": why,
        "collision_entity": int(result.collision_entity[0]) if collided else None,
    }  # fmt: skip


def _step_why(result: Any, s: int, s_hit: int | None, cost: np.ndarray, req: Any) -> str:
    """Why step ``s`` is invalid, in the words of ``/v1/whatif`` where it says the same."""
    x, y = result.xy[0, s]
    at = f"at ({x:.1f}, {y:.1f}) m at t={float(result.t_s[s]):.1f} s"
    if s == s_hit:
        return f"collides with entity {int(result.collision_entity[0])} at t={result.t_s[s]:.1f} s"
    trav = float(result.traversability[0, s])
    if math.isfinite(trav) and trav <= 0.0:
        return f"blocked cell {at}"
    if cost[s] < req.max_cost:  # invalid only for its unknown cells
        return f"unknown cells under the footprint {at} (consider_unknown_as_obstacle)"
    return f"cost {int(cost[s])} >= max_cost {req.max_cost} {at} (traversability {trav:.2f})"


# --- the routes --------------------------------------------------------------------------------


def add_ros_routes(app: FastAPI, live: Any) -> None:
    """Add the three ROS-shaped endpoints (module docstring) over ``live`` (a
    :class:`wm.serve.LiveNode`) to ``app``."""

    @app.post("/v1/grid_map/get_grid_map")
    def get_grid_map(req: GetGridMapRequest, response: Response) -> GetGridMapAnswer:
        """grid_map_msgs/srv/GetGridMap: the submap of ``length_x`` x ``length_y`` m around
        (``position_x``, ``position_y``) world m of map ``level`` (extension), the ``layers``
        asked (all when empty; an earlier name such as ``z_m2`` stands for the current one,
        named in ``renamed_layers``), column-major with index (0, 0) at the largest x and y
        (module docstring of wm.serve_ros). From the cycle's copy when it holds the layers
        (:func:`wm.serve_views.read_level`)."""
        check_frame(req.frame_id, "request")
        renamed: dict[str, str] = {}

        def layers_of(lvl: Any) -> list[str]:
            layers, got = _grid_layers(lvl, req.layers)
            renamed.update(got)
            _check_grid_window(lvl, req, layers)
            return layers

        def window(src: LevelRead) -> tuple[MapWindow, int]:
            w = map_window(src.level, req.position_x, req.position_y, 0.5 * req.length_x,
                           src.layers, half_y_m=0.5 * req.length_y)  # fmt: skip
            return w, src.cycle_t_ns

        w, cycle = read_level(live, req.level, layers_of, window)
        response.headers.update(renamed_headers(renamed))
        return {"map": grid_map_of(w, cycle), "cycle_t_ns": cycle, "frame": WORLD,
                "level": w.level, "renamed_layers": renamed}  # fmt: skip

    @app.post("/v1/elevation_mapping/check_safety")
    def check_safety(req: CheckSafetyRequest) -> CheckSafetyAnswer:
        """elevation_map_msgs/srv/CheckSafety: per polygon (world m) whether it is safe to be
        on, its mean traversability, and (``compute_untraversable_polygon``) the hull of what
        is not; ``why`` per polygon (module docstring of wm.serve_ros)."""
        polys = [_polygon_xy(p, k) for k, p in enumerate(req.polygons)]

        def layers_of(lvl: Any) -> list[str]:
            _check_polygon_cells(lvl, polys)
            return ["traversability"]

        # the entities' boxes and a copy of each polygon's cells (at most MAX_BINARY_VALUES in
        # all), from the cycle's copy (or, for a level whose traversability it does not hold,
        # under the node's lock); the verdicts, which test every cell, come after either way
        def inputs(src: LevelRead) -> tuple[str, int, Any, list[MapWindow]]:
            boxes = _entity_boxes(source_what_if(src), polys, src.cycle_t_ns)
            windows = [polygon_window(src.level, poly) for poly in polys]
            return src.level.name, src.cycle_t_ns, boxes, windows

        level, cycle, boxes, windows = read_level(live, req.level, layers_of, inputs)
        out = [
            polygon_safety(w, boxes, poly, p.polygon.points[0].z,
                           req.compute_untraversable_polygon, cycle)
            for w, poly, p in zip(windows, polys, req.polygons, strict=True)
        ]  # fmt: skip
        return {
            "is_safe": [o["is_safe"] for o in out],
            "traversability": [o["traversability"] for o in out],
            "untraversable_polygons": [o["untraversable_polygon"] for o in out],
            "why": [o["why"] for o in out], "known_fraction": [o["known_fraction"] for o in out],
            "cycle_t_ns": cycle, "frame": WORLD, "level": level,
        }  # fmt: skip

    @app.post("/v1/nav2/is_path_valid")
    def is_path_valid(req: IsPathValidRequest) -> IsPathValidAnswer:
        """nav2_msgs/srv/IsPathValid: the path rolled out by What If from the present (as
        ``/v1/whatif`` rolls out ``plan``); the first invalid pose (or all) where the rollout
        is blocked, collides, or costs ``max_cost`` or more; ``why`` (module docstring of
        wm.serve_ros)."""
        from wm.serve import published, what_if_over
        from wm.whatif import WaypointPlan, WhatIfError

        for name in ("layer_name", "footprint"):
            if getattr(req, name):
                raise HTTPException(
                    400, f"{name} {getattr(req, name)!r}: only '' (What If's whole judgment "
                    "with the vehicle model's footprint) is served",
                )  # fmt: skip
        xy, stamps = _path_arrays(req.path)
        # from the newest cycle's copy, as /v1/whatif: never waits for the cycle in progress
        snap = published(live)
        cycle = snap.cycle_t_ns
        wi = what_if_over(snap)
        try:
            start = wi.start_from_kd()
            first, end = judged_span(xy, start.xy, req.max_lookahead_distance)
            speed = path_speed(start.speed_mps, wi.vehicle)
            t_pose = path_schedule(xy, stamps, first, end, speed)
            t_s, wp = _waypoints(xy[first:end], t_pose)
            dt = wi.config.steps_s.get(req.level, math.nan)
            horizon = plan_horizon_s(t_s, wp, dt, wi.vehicle)
            plan = WaypointPlan(t_s, wp, "path")
            result = wi.simulate([plan], level=req.level, start=start, horizon_s=horizon)
        except WhatIfError as e:
            raise HTTPException(400, str(e)) from None
        verdict = judge_path(req, result, xy[:end], t_pose, first)
        return {
            "success": True, **verdict, "first_pose_index": first, "end_pose_index": end,
            "end_gap_m": float(np.linalg.norm(result.xy[0, -1] - xy[end - 1])),
            "plan": {"name": plan.name, "t_s": t_s.tolist(), "xy": wp.tolist()},
            "horizon_s": horizon, "cycle_t_ns": cycle, "frame": WORLD, "level": result.level,
        }  # fmt: skip
