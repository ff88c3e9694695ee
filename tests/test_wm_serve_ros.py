"""The ROS-shaped endpoints of the live node (wm.serve_ros: GetGridMap, CheckSafety,
IsPathValid) over real HTTP on localhost (uvicorn), after the replay of a simulated log:
grid maps against the node's own map levels and the /v1/maps windows, safety against the
simulator's truth boxes, path validity against /v1/whatif. The log and the request helper are
test_wm_serve's."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from serving import MODES, holding_node_lock, level_cells, node_lock_held, start_live
from serving import served as served_app

pytest.importorskip("fastapi")
uvicorn = pytest.importorskip("uvicorn")

from test_wm_serve import TOKEN, call, log  # noqa: E402, F401  (log: a fixture)

GRID = "/v1/grid_map/get_grid_map"
SAFETY = "/v1/elevation_mapping/check_safety"
PATH = "/v1/nav2/is_path_valid"


@pytest.fixture(scope="module", params=MODES)
def served(log: Path, tmp_path_factory, request):  # noqa: F811 (test_wm_serve's fixture)
    """A live node that has replayed the whole log (as fast as it can), in a process of its
    own and in a thread of this one, served on a free localhost port: every test sees the
    same, final, cycle."""
    from wm.serve import create_app

    kd_path = tmp_path_factory.mktemp("ros-kd") / "live.duckdb"
    live = start_live(log, kd_path, rate=0.0, mode=request.param)
    assert live.wait(600) and not live.status.error, live.status.error
    with served_app(create_app(live, token=TOKEN)) as base:
        yield live, base
    live.stop()


def _self(base: str) -> dict:
    code, me = call(base, "/v1/self")
    assert code == 200, me
    return me


# --- GetGridMap --------------------------------------------------------------------------------


def _grid_matrix(arr: dict) -> np.ndarray:
    """A Float32MultiArray read as grid_map reads it (GridMapMsgHelpers: column-major when
    dim[0] is "column_index"): the matrix M (rows, cols), None as NaN."""
    col, row = arr["layout"]["dim"]
    assert col["label"] == "column_index" and row["label"] == "row_index"
    data = np.array(arr["data"], dtype=np.float64)  # None -> NaN
    return data.reshape(col["size"], row["size"]).T  # data[j rows + i] = M[i, j]


def _grid_centres(m: dict) -> np.ndarray:
    """World xy (rows, cols, 2) m of every cell M[i, j], by grid_map's convention
    (getPositionFromIndex): index (0, 0) at the largest x and y, i along -x, j along -y."""
    info = m["info"]
    res, p = info["resolution"], info["pose"]["position"]
    col, row = m["data"][0]["layout"]["dim"]
    i, j = np.meshgrid(np.arange(row["size"]), np.arange(col["size"]), indexing="ij")
    x = p["x"] + 0.5 * info["length_x"] - 0.5 * res - i * res
    y = p["y"] + 0.5 * info["length_y"] - 0.5 * res - j * res
    return np.stack([x, y], axis=-1)


def test_grid_map_layout_of_a_synthetic_window() -> None:
    """grid_map_of alone: every value lands at the index whose grid_map position is its cell
    centre, with grid_map's dims and strides, on a window whose values all differ."""
    from wm.serve_ros import grid_map_of
    from wm.serve_views import MapWindow

    ny, nx, res = 3, 5, 0.5
    w_vals = np.arange(ny * nx, dtype=np.float32).reshape(ny, nx)  # row north, col east
    w = MapWindow("test", res, (10.0, -2.0), {"v": w_vals}, ((0, 0), (1, 1)))
    m = grid_map_of(w, 1_500_000_007)
    assert m["header"] == {"stamp": {"sec": 1, "nanosec": 500_000_007}, "frame_id": "world"}
    assert m["data"][0]["layout"] == {
        "dim": [
            {"label": "column_index", "size": ny, "stride": nx * ny},
            {"label": "row_index", "size": nx, "stride": nx},
        ],
        "data_offset": 0,
    }
    M = _grid_matrix(m["data"][0])
    assert M.shape == (nx, ny)  # rows along x
    xy = _grid_centres(m)
    c = np.floor((xy[..., 0] - 10.0) / res).astype(int)
    r = np.floor((xy[..., 1] + 2.0) / res).astype(int)
    np.testing.assert_array_equal(M, w_vals[r, c])
    assert M[0, 0] == w_vals[-1, -1]  # north-east corner first
    assert m["info"]["pose"]["position"] == {"x": 11.25, "y": -1.25, "z": 0.0}


def _window_value(w: dict, layer: str, xy: np.ndarray) -> np.ndarray:
    """The /v1/maps JSON window's values at world points xy (..., 2) (the cell holding each)."""
    res, (ox, oy) = w["resolution_m"], w["origin"]
    vals = np.array(w["values"][layer], dtype=np.float64)
    c = np.floor((xy[..., 0] - ox) / res).astype(int)
    r = np.floor((xy[..., 1] - oy) / res).astype(int)
    return vals[r, c]


@pytest.mark.parametrize(
    ("dx", "length_x", "length_y"),
    [(0.13, 8.0, 8.0), (0.13, 8.0, 5.2), (None, 20.0, 9.0)],
    ids=["square", "wide", "past-the-level-edge"],
)
def test_grid_map_values_are_the_map_window_values(served, dx, length_x, length_y) -> None:
    """A submap around the vehicle (and one half past the level's scrolling window): each
    M[i, j] equals the node's level at the cell grid_map places it at, and the /v1/maps window
    there; dims, strides, header, cycle as grid_map and the API say; the client agrees."""
    from wm.client import Client

    live, base = served
    me = _self(base)
    x, y = me["position"][:2]
    layers = ["elevation", "traversability", "entity_id"]
    half = 0.5 * max(length_x, length_y)
    _, w = call(base, f"/v1/maps/subsystem?x={x}&y={y}&half_m={half}&layers=elevation")
    if dx is None:  # centred on the level's east edge: half the cells beyond it
        x = w["level_bounds"][1][0]
    else:
        x += dx
    req = {"position_x": x, "position_y": y, "length_x": length_x, "length_y": length_y,
           "layers": layers}  # fmt: skip
    code, ans = call(base, GRID, req)
    assert code == 200, ans
    m = ans["map"]
    assert ans["cycle_t_ns"] == live.status.cycle_t_ns and ans["frame"] == "world"
    assert m["header"]["stamp"] == {"sec": ans["cycle_t_ns"] // 10**9,
                                    "nanosec": ans["cycle_t_ns"] % 10**9}  # fmt: skip
    assert m["header"]["frame_id"] == "world" and m["layers"] == layers
    assert m["outer_start_index"] == 0 and m["inner_start_index"] == 0
    info = m["info"]
    nx, ny = (2 * math.ceil(0.5 * v / 0.4) + 1 for v in (length_x, length_y))
    assert info["resolution"] == 0.4
    assert (info["length_x"], info["length_y"]) == pytest.approx((nx * 0.4, ny * 0.4))
    assert info["pose"]["orientation"] == {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
    for arr in m["data"]:
        assert arr["layout"]["dim"] == [
            {"label": "column_index", "size": ny, "stride": nx * ny},
            {"label": "row_index", "size": nx, "stride": nx},
        ]
        assert arr["layout"]["data_offset"] == 0 and len(arr["data"]) == nx * ny
    xy = _grid_centres(m)
    _, win = call(base, f"/v1/maps/subsystem?x={x}&y={y}&half_m={half}&layers={','.join(layers)}")
    cells = live.call(level_cells, "subsystem", layers, xy.reshape(-1, 2))
    for layer, arr in zip(layers, m["data"], strict=True):
        M = _grid_matrix(arr)
        want = cells[layer].astype(np.float64).reshape(M.shape)
        np.testing.assert_array_equal(M, want)
        np.testing.assert_array_equal(M, _window_value(win, layer, xy))
    elev = _grid_matrix(m["data"][0])
    if dx is None:  # past the edge: empty cells (null, -1) beside known ones
        beyond = xy[..., 0] > win["level_bounds"][1][0]
        assert beyond.any() and np.isfinite(elev[~beyond]).any()
        assert np.isnan(elev[beyond]).all() and (_grid_matrix(m["data"][2])[beyond] == -1).all()
    else:
        assert np.isfinite(elev).mean() > 0.5
    c = Client(base, TOKEN)
    assert c.get_grid_map(x, y, length_x, length_y, tuple(layers)) == ans


def test_grid_map_gives_every_layer_when_none_is_asked(served) -> None:
    _, base = served
    me = _self(base)
    x, y = me["position"][:2]
    code, ans = call(base, GRID, {"position_x": x, "position_y": y, "length_x": 2, "length_y": 2})
    assert code == 200, ans
    from maps.layers import DEFAULT_LAYERS

    assert ans["map"]["layers"] == [s.name for s in DEFAULT_LAYERS]
    assert len(ans["map"]["data"]) == len(DEFAULT_LAYERS)


# --- CheckSafety -------------------------------------------------------------------------------


def _truth_in_kd_world(live, log_path: Path):
    """(truth, T_est_true at the self state's time, that time): the truth boxes move into the
    KD's world with ``T_est_true`` (tests/alignment.py)."""
    from core.geometry import quat_to_matrix, se3, se3_inverse
    from wm.evaluation import load_truth

    truth = load_truth(log_path)
    s = live.call(_self_state)
    T_est = se3(quat_to_matrix(s.orientation_xyzw), s.position_xyz)
    return truth, T_est @ se3_inverse(truth.poses.at(s.t_ns)), int(s.t_ns)


def _self_state(live):
    """The KD's self state (a :meth:`wm.serve.LiveNode.call`)."""
    with live.lock:
        return live.kd.get(live.node.self_id).state


def _polygon(corners: np.ndarray, z: float = 0.0) -> dict:
    pts = [{"x": float(x), "y": float(y), "z": z} for x, y in corners]
    return {"header": {"frame_id": "world"}, "polygon": {"points": pts}}


def test_check_safety_around_true_objects_and_on_open_ground(served, log) -> None:  # noqa: F811
    """Polygons around the simulator's static objects near the vehicle that its last sweep saw
    (their true footprints grown by 0.5 m, in the KD's world) are unsafe, naming an entity or
    a blocked cell, with an untraversable hull near the object; a polygon on the ground the
    vehicle drove over a second ago, no object within 5 m, is safe, its cells known and
    passable."""
    from alignment import move_boxes, move_points

    from maps.submap import inside_polygon
    from wm.client import Client
    from wm.evaluation import EvalConfig
    from wm.serve_ros import box_corners

    live, base = served
    truth, T, t = _truth_in_kd_world(live, log)
    # the box set of the last sweep, which says how many of its returns hit each object
    k_last = max(
        i for i, b in enumerate(truth.boxes) if b.n_returns is not None and truth.box_t_ns[i] <= t
    )
    boxes = move_boxes(truth.boxes[k_last], T)
    me = np.array(_self(base)["position"][:2])
    dist = np.linalg.norm(boxes.centers[:, :2] - me, axis=1)
    still = np.linalg.norm(np.nan_to_num(boxes.velocities[:, :2]), axis=1) < 0.1
    # seen as the evaluation protocol counts it (docs/evaluation.md): a post 36 m off with two
    # returns a sweep is no object a user can expect the KD to hold
    seen = boxes.n_returns >= EvalConfig().min_points
    near = np.flatnonzero(still & seen & (dist < 40.0))  # well inside the 102 m subsystem window
    assert near.size, "no static true object seen within 40 m of the vehicle"
    polys = [
        box_corners(boxes.centers[k], boxes.sizes[k, 0] + 1.0, boxes.sizes[k, 1] + 1.0,
                    boxes.yaws[k])
        for k in near
    ]  # fmt: skip
    body = {"polygons": [_polygon(p, 1.5) for p in polys], "compute_untraversable_polygon": True}
    code, ans = call(base, SAFETY, body)
    assert code == 200, ans
    assert ans["frame"] == "world" and ans["cycle_t_ns"] == live.status.cycle_t_ns
    assert len(ans["is_safe"]) == len(ans["untraversable_polygons"]) == len(near)
    for k, poly in enumerate(polys):
        assert ans["is_safe"][k] is False, (boxes.classes[near[k]], ans["why"][k])
        assert ans["why"][k].startswith(("entity", "entities", "blocked cell"))
        hull = ans["untraversable_polygons"][k]
        pts = np.array([[p["x"], p["y"]] for p in hull["polygon"]["points"]])
        assert len(pts) >= 3 and all(p["z"] == 1.5 for p in hull["polygon"]["points"])
        assert hull["header"]["frame_id"] == "world"
        # the hull covers what is untraversable in the polygon: some of it lies inside it
        assert inside_polygon(pts, poly).any() or inside_polygon(poly, pts).any()
    # the objects are perceived: an entity of the KD makes at least one of them unsafe
    assert any(w.startswith("entit") for w in ans["why"]), ans["why"]
    without = call(base, SAFETY, body | {"compute_untraversable_polygon": False})[1]
    assert without["is_safe"] == ans["is_safe"] and without["why"] == ans["why"]
    assert all(not p["polygon"]["points"] for p in without["untraversable_polygons"])

    behind = move_points(T, truth.poses.at(t - 1_000_000_000)[:3, 3])[:2]
    assert np.linalg.norm(behind - me) > 5.0  # it moved: this is ground it drove over
    assert np.linalg.norm(boxes.centers[:, :2] - behind, axis=1).min() > 5.0
    square = behind + np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    code, ok = call(base, SAFETY, {"polygons": [_polygon(square)]})
    assert code == 200, ok
    assert ok["is_safe"] == [True] and ok["why"][0].startswith("clear"), ok["why"]
    assert ok["known_fraction"][0] >= 0.9 and 0.0 < ok["traversability"][0] <= 1.0
    c = Client(base, TOKEN)
    assert c.check_safety([[tuple(p) for p in square]]) == ok


def _reference_safety(
    live, polys: list[np.ndarray], z: float, hull: bool, level: str = "subsystem"
) -> dict:
    """CheckSafety as it was first written, under the node's lock throughout: every cell of
    the polygon's bounding-box window tested against every edge, every box against the
    polygon by :func:`maps.submap.inside_polygon`; the answer's shape. Worked out where the
    node is (:meth:`wm.serve.LiveNode.call`)."""
    return live.call(_reference_safety_on, polys, z, hull, level)


def _reference_safety_on(live, polys: list[np.ndarray], z: float, hull: bool, level: str) -> dict:
    from maps.submap import inside_polygon
    from wm import serve_ros as ros
    from wm.serve_views import find_level, map_window

    out = []
    with live.lock:
        lvl, cycle = find_level(live.node.stack, level), live.snapshot.cycle_t_ns
        boxes = ros._entity_boxes(ros.node_what_if(live.node), polys, cycle)
        for poly in polys:
            lo, hi = poly.min(axis=0), poly.max(axis=0)
            c, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
            w = map_window(lvl, c[0], c[1], half[0], ["traversability"], half_y_m=half[1])
            ny, nx = w.shape
            rows, cols = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
            res, (ox, oy) = w.resolution_m, w.origin_xy
            xy = np.stack([ox + (cols.ravel() + 0.5) * res, oy + (rows.ravel() + 0.5) * res], 1)
            trav = w.values["traversability"].astype(np.float64).ravel()
            inside = inside_polygon(xy, poly)
            if not inside.any():
                inside[np.argmin(np.linalg.norm(xy - poly.mean(axis=0), axis=1))] = True
            trav, xy = trav[inside], xy[inside]
            hits = []
            for k in range(len(boxes)):
                bc = ros.box_corners(boxes.centers_xyz[k], *boxes.sizes_lwh[k, :2], boxes.yaws[k])
                if (
                    inside_polygon(bc, poly).any()
                    or inside_polygon(poly, bc).any()
                    or ros._segments_cross(bc, np.roll(bc, -1, 0), poly, np.roll(poly, -1, 0))
                ):
                    hits.append((int(boxes.ids[k]), bc))
            known = np.isfinite(trav)
            blocked = known & (trav <= 0.0)
            pts = ros._untraversable_points(hits, xy[blocked], w.resolution_m, z) if hull else []
            out.append({
                "is_safe": bool(known.any() and not blocked.any() and not hits),
                "traversability": float(trav[known].mean()) if known.any() else None,
                "untraversable_polygon": {"header": ros.header_of(cycle),
                                          "polygon": {"points": pts}},
                "why": ros._safety_why(hits, trav, xy), "known_fraction": float(known.mean()),
            })  # fmt: skip
    keys = ("is_safe", "traversability", "untraversable_polygon", "why", "known_fraction")
    return {k: [o[k] for o in out] for k in keys}


def _safety_polygons(centre: np.ndarray) -> list[np.ndarray]:
    """Polygons around ``centre`` (world m): boxes, circles, a concave L and a star, rotated
    and of many sizes, some smaller than a cell (the nearest cell stands in), some reaching
    beyond the map level's window."""
    from wm.serve_ros import box_corners

    rng = np.random.default_rng(7)
    polys = []
    for k in range(40):
        c = centre + rng.uniform(-45.0, 45.0, 2)
        r = float(rng.choice([0.1, 1.0, 3.0, 8.0, 30.0]))
        kind = k % 4
        if kind == 0:
            polys.append(box_corners(c, 2 * r, r, float(rng.uniform(-3, 3))))
        elif kind == 1:
            a = np.linspace(0.0, 2 * np.pi, 37)[:-1]
            polys.append(c + r * np.stack([np.cos(a), np.sin(a)], axis=1))
        elif kind == 2:
            L = np.array([[0, 0], [4, 0], [4, 1], [1, 1], [1, 4], [0, 4]], dtype=float)
            polys.append(c + 0.25 * r * L)
        else:
            a = np.linspace(0.0, 2 * np.pi, 15)[:-1] + float(rng.uniform(0, 1))
            rad = np.where(np.arange(14) % 2 == 0, r, 0.4 * r)
            polys.append(c + rad[:, None] * np.stack([np.cos(a), np.sin(a)], axis=1))
    return polys


def test_check_safety_answers_as_the_reference(served) -> None:
    """The verdicts worked out outside the node's lock, from a copy of each polygon's cells,
    are those of the first implementation (every cell against every edge, under the lock),
    field by field, on polygons of every shape around the vehicle, some holding entities and
    blocked cells, with and without the untraversable hull."""
    live, base = served
    polys = _safety_polygons(np.array(_self(base)["position"][:2]))
    for hull in (True, False):
        body = {"polygons": [_polygon(p, 0.5) for p in polys],
                "compute_untraversable_polygon": hull}  # fmt: skip
        code, ans = call(base, SAFETY, body)
        assert code == 200, ans
        want = _reference_safety(live, polys, 0.5, hull)
        assert ans["untraversable_polygons"] == want["untraversable_polygon"]
        for key in ("is_safe", "traversability", "why", "known_fraction"):
            assert ans[key] == want[key], key
    # the case exercises what it should: safe and unsafe polygons, entities, blocked cells
    assert True in ans["is_safe"] and False in ans["is_safe"]
    assert any(w.startswith("entit") for w in ans["why"]), ans["why"]
    assert any(w.startswith("blocked") for w in ans["why"]), ans["why"]


class _Entries:
    """A stand-in for the node's lock that counts how often it was taken."""

    def __init__(self, lock) -> None:
        self.lock, self.entered = lock, 0

    def __enter__(self) -> None:
        self.lock.acquire()
        self.entered += 1

    def __exit__(self, *exc) -> None:
        self.lock.release()

    def locked(self) -> bool:
        return self.lock.locked()


def test_large_check_safety_never_takes_the_node_lock(served, monkeypatch) -> None:
    """A CheckSafety at the size limit (100 polygons of 100 points over about 1 000 000
    cells) reads the cycle's copy (its traversability and entity boxes): the node's lock is
    never taken (it used to be held throughout, about 2 s, stalling the node's cycle, and then
    for the copy of every polygon's cells), and every verdict is worked out with it free."""
    import wm.serve_ros as ros

    live, base = served
    me = np.array(_self(base)["position"][:2])
    res = 0.4  # the subsystem level's cells, m; the limit is checked below
    half = 0.5 * 98 * res  # each polygon's bounding box 99 x 99 cells
    a = np.linspace(0.0, 2 * np.pi, 101)[:-1]
    circle = half * np.stack([np.cos(a), np.sin(a)], axis=1)
    polys = [me + 2.2 * half * np.array([k % 10 - 4.5, k // 10 - 4.5]) + circle
             for k in range(100)]  # fmt: skip
    judged_locked = []
    judge = ros.polygon_safety

    def watched(*args, **kw):
        judged_locked.append(live.lock.locked())
        return judge(*args, **kw)

    monkeypatch.setattr(ros, "polygon_safety", watched)
    entries = _Entries(live.lock)
    monkeypatch.setattr(live, "lock", entries)
    calls = []  # requests to the node itself: none either (in its process, when in one)
    to_node = live.call
    monkeypatch.setattr(live, "call", lambda *a, **kw: calls.append(a) or to_node(*a, **kw))
    body = {"polygons": [_polygon(p) for p in polys], "compute_untraversable_polygon": True}
    code, ans = call(base, SAFETY, body)
    assert code == 200, ans
    assert len(ans["is_safe"]) == 100 and judged_locked == [False] * 100
    # near the limit: a polygon of twice the area is refused
    assert call(base, SAFETY, {"polygons": [_polygon(2 * circle + me)] * 100})[0] == 413
    assert entries.entered == 0 and calls == []


def test_polygon_geometry_helpers() -> None:
    """Point in polygon (a concave one), box overlap by corner, by edges crossing only, and
    apart; a convex hull."""
    from maps.submap import inside_polygon
    from wm.serve_ros import box_corners, box_overlaps_polygon, convex_hull

    L = np.array([[0, 0], [4, 0], [4, 1], [1, 1], [1, 4], [0, 4]], dtype=float)  # an L
    got = inside_polygon(np.array([[0.5, 3.0], [3.0, 0.5], [3.0, 3.0], [5.0, 0.5]]), L)
    assert got.tolist() == [True, True, False, False]
    assert box_overlaps_polygon(box_corners(np.array([3.0, 0.5]), 1.0, 0.5, 0.0), L)
    # a thin box across the L's arm: no corner inside either, the edges cross
    assert box_overlaps_polygon(box_corners(np.array([2.0, 0.5]), 0.2, 3.0, 0.0), L)
    assert not box_overlaps_polygon(box_corners(np.array([3.0, 3.0]), 1.0, 1.0, 0.3), L)
    hull = convex_hull(np.array([[0, 0], [2, 0], [1, 1], [2, 2], [0, 2], [1, 0.5]], float))
    assert sorted(map(tuple, hull.tolist())) == [(0, 0), (0, 2), (2, 0), (2, 2)]


def test_grid_and_point_tests_match_inside_polygon() -> None:
    """The cell test CheckSafety uses (crossings per row) and its few-point test give
    maps.submap.inside_polygon's answers exactly, on random convex, star-shaped and
    self-crossing polygons, some with vertices on the cell centres' lines, near and far
    from the origin."""
    from maps.submap import inside_polygon
    from wm.serve_ros import _inside_grid, _inside_points

    rng = np.random.default_rng(0)
    for trial in range(200):
        k = int(rng.integers(3, 40))
        c = rng.uniform(-1e3, 1e3, 2) * (1e5 if trial % 7 == 0 else 1.0)
        a = np.sort(rng.uniform(0.0, 2 * np.pi, k))
        r = rng.uniform(0.5, 20.0, k)
        poly = c + np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
        if trial % 3 == 0:  # any vertex order, on a lattice of the cells' size
            poly = np.round(c + rng.uniform(-20.0, 20.0, (k, 2)) / 0.4) * 0.4
        res = [0.1, 0.4, 0.25, 1.0][trial % 4]
        ox, oy = np.floor((poly.min(axis=0) - 3.0) / res) * res
        nx, ny = (int(n) for n in rng.integers(5, 120, 2))
        xc, yr = ox + (np.arange(nx) + 0.5) * res, oy + (np.arange(ny) + 0.5) * res
        xy = np.stack(np.broadcast_arrays(xc[None, :], yr[:, None]), axis=-1).reshape(-1, 2)
        assert (_inside_grid(xc, yr, poly).ravel() == inside_polygon(xy, poly)).all(), trial
        few = xy[rng.choice(len(xy), 50)]
        assert (_inside_points(few, poly) == inside_polygon(few, poly)).all(), trial


# --- IsPathValid -------------------------------------------------------------------------------


def _expected_pose(xy: np.ndarray, t_pose: np.ndarray, p: np.ndarray, t: float) -> int:
    """The documented rule: the pose nearest the rollout position ``p`` among those due by
    time ``t`` (the one being driven to included)."""
    due = min(int(np.searchsorted(t_pose, t - 1e-9)), len(t_pose) - 1)
    return int(np.argmin(np.linalg.norm(xy[: due + 1] - p, axis=1)))


def _path(points: np.ndarray, stamps_s: list[float] | None = None) -> dict:
    poses = []
    for k, (x, y) in enumerate(points):
        stamp = {"sec": 0, "nanosec": 0}
        if stamps_s is not None:
            ns = round(stamps_s[k] * 1e9)
            stamp = {"sec": ns // 10**9, "nanosec": ns % 10**9}
        poses.append({"header": {"stamp": stamp, "frame_id": "world"},
                      "pose": {"position": {"x": float(x), "y": float(y), "z": 0.0}}})  # fmt: skip
    return {"header": {"frame_id": "world"}, "poses": poses}


def _judge_both(base: str, points: np.ndarray, **extra) -> tuple[dict, dict]:
    """(IsPathValid's answer, /v1/whatif's plan for the plan it says it rolled out)."""
    code, ans = call(base, PATH, {"path": _path(points), **extra})
    assert code == 200, ans
    body = {"plans": [ans["plan"]], "level": ans["level"], "horizon_s": ans["horizon_s"]}
    code, wi = call(base, "/v1/whatif", body)
    assert code == 200, wi
    return ans, wi


def _check_agreement(ans: dict, wi: dict, points: np.ndarray) -> None:
    """IsPathValid says what /v1/whatif says of the same rollout (module docstring rule)."""
    plan, w = ans["plan"], wi["plans"][0]
    assert ans["success"] is True and ans["frame"] == "world"
    assert ans["collision_entity"] == w["collision_entity"]
    assert ans["is_valid"] == (not ans["invalid_pose_indices"])
    first = ans["first_pose_index"]
    np.testing.assert_allclose(plan["xy"], points[first : ans["end_pose_index"]])
    if w["collision_entity"] is not None:
        assert not ans["is_valid"]
    if ans["is_valid"]:
        assert ans["why"] == w["why"] and w["why"].startswith("clear")
        return
    # the first invalid step's time is in our why; /v1/whatif's rollout has its position there
    t = (
        w["collision_t_s"]
        if ans["why"].startswith("collides")
        else float(ans["why"].rsplit("t=", 1)[1].split(" s")[0])
    )
    step = round(t / wi["dt_s"])
    p = np.array(w["xy"][step])
    want = first + _expected_pose(points[first:], np.array(plan["t_s"]), p, t)
    assert ans["invalid_pose_indices"][0] == want
    if ans["why"].startswith("collides") or w["collision_entity"] is None:
        assert ans["why"] == w["why"]  # the same first event, in the same words


def test_is_path_valid_agrees_with_what_if(served) -> None:
    """Straight paths from the vehicle through each confirmed object within 45 m and 5 m
    beyond, and a fan of short paths ahead: every answer agrees with /v1/whatif on the same
    rollout (collision, first invalid pose, why); no path whose rollout meets an object is
    valid (one far off the vehicle's heading may be driven past it), and one
    whose first event is its object is invalid at the pose where the rollout meets it, the
    first pose that near it; a path /v1/whatif calls clear, which the rollout follows, is
    valid."""
    from wm.client import Client

    _, base = served
    me = _self(base)
    xy0 = np.array(me["position"][:2])
    q = f"/v1/entities?x={xy0[0]}&y={xy0[1]}&radius_m=45&level=4&status=confirmed"
    code, reg = call(base, q)
    assert code == 200, reg
    objs = [e for e in reg["entities"] if e["entity_id"] != me["entity_id"]]
    assert objs, "no confirmed object within 45 m"
    hits, through = [], 0
    for e in objs:
        target = np.array(e["position"][:2])
        d = float(np.linalg.norm(target - xy0))
        points = xy0 + (target - xy0) / d * np.arange(0.0, d + 5.0, 1.0)[:, None]
        ans, wi = _judge_both(base, points)
        _check_agreement(ans, wi, points)
        # a path far off the vehicle's heading is not driven as drawn at its speed: the
        # rollout swings wide and may pass the object; one that meets it is never valid
        roll = np.array(wi["plans"][0]["xy"])
        met = wi["plans"][0]["collision_entity"] == e["entity_id"]
        if met or np.linalg.norm(roll - target, axis=1).min() < 1.0:
            through += 1
            assert not ans["is_valid"], (e, ans)  # no path through an object is valid
        if ans["why"].startswith(f"collides with entity {e['entity_id']} at"):
            hits.append((ans, points, target))
    assert through, "no rollout through a confirmed object"
    # a path may meet a blocked cell (a slope, a bush's cells) before its object: the first
    # event is then that cell, as /v1/whatif says too (checked above); a path that meets its
    # object first does so at the pose nearest it
    for ans, points, target in hits:
        k = ans["invalid_pose_indices"][0]
        gap = np.linalg.norm(points - target, axis=1)
        assert gap[k] < 8.0 and (gap[:k] > gap[k]).all()  # it meets the object there
        every = call(base, PATH, {"path": _path(points), "stop_at_first_collision": False})[1]
        assert every["invalid_pose_indices"][0] <= k and k in every["invalid_pose_indices"]
        assert every["invalid_pose_indices"] == sorted(set(every["invalid_pose_indices"]))

    heading = math.atan2(*me["velocity"][1::-1])
    free = None
    for turn in np.radians([0, 10, -10, 20, -20, 30, -30]):
        for length in (12.0, 8.0):
            u = np.array([math.cos(heading + turn), math.sin(heading + turn)])
            points = xy0 + u * np.arange(0.0, length + 0.5, 1.0)[:, None]
            ans, wi = _judge_both(base, points)
            _check_agreement(ans, wi, points)
            roll = np.array(wi["plans"][0]["xy"])
            followed = np.linalg.norm(points[:, None] - roll[None], axis=2).min(axis=1).max()
            if wi["plans"][0]["why"].startswith("clear") and followed < 1.0:
                free = ans
                break
        if free is not None:
            break
    assert free is not None, "no clear path ahead that the rollout follows"
    assert free["is_valid"] and free["invalid_pose_indices"] == []
    assert Client(base, TOKEN).is_path_valid([tuple(p) for p in points]) == free


def test_is_path_valid_uses_stamps_and_lookahead(served) -> None:
    """Stamped poses are the plan's schedule (s after the closest pose's stamp); poses before
    the one closest to the vehicle are not judged; max_lookahead_distance ends the judged span
    at the first pose beyond it along the path."""
    _, base = served
    me = _self(base)
    xy0 = np.array(me["position"][:2])
    heading = math.atan2(*me["velocity"][1::-1])
    u = np.array([math.cos(heading), math.sin(heading)])
    points = xy0 + u * np.arange(-3.0, 10.0, 1.0)[:, None]  # three poses behind the vehicle
    stamps = [100.0 + 0.25 * k for k in range(len(points))]
    code, ans = call(base, PATH, {"path": _path(points, stamps)})
    assert code == 200, ans
    assert ans["first_pose_index"] == 3 and ans["end_pose_index"] == len(points)
    np.testing.assert_allclose(ans["plan"]["t_s"], 0.25 * np.arange(len(points) - 3), atol=1e-9)
    assert all(i >= 3 for i in ans["invalid_pose_indices"])
    code, ans = call(base, PATH, {"path": _path(points), "max_lookahead_distance": 4.5})
    assert code == 200, ans
    assert (ans["first_pose_index"], ans["end_pose_index"]) == (3, 8)  # 0..4 m ahead


# --- bad requests ------------------------------------------------------------------------------


def _grid(**kw) -> dict:
    return {"position_x": 0.0, "position_y": 0.0, "length_x": 4.0, "length_y": 4.0,
            "layers": ["elevation"]} | kw  # fmt: skip


def _poly(points: list, frame: str = "world") -> dict:
    pts = [{"x": x, "y": y} for x, y in points]
    return {"polygons": [{"header": {"frame_id": frame}, "polygon": {"points": pts}}]}


SQUARE = [(0, 0), (1, 0), (1, 1), (0, 1)]


@pytest.mark.parametrize(
    ("path", "body", "code", "names"),
    [
        (GRID, _grid(frame_id="odom"), 400, "frame_id 'odom'"),
        (GRID, _grid(position_x=float("nan")), 422, "position_x"),
        (GRID, _grid(position_y=1e300), 422, "position_y"),
        (GRID, _grid(length_x=0.0), 422, "length_x"),
        (GRID, _grid(length_y=float("inf")), 422, "length_y"),
        (GRID, _grid(length_x=1e6), 413, "length_x=1000000.0"),
        (GRID, _grid(layers=[], length_x=10.0, length_y=10.0), 413, "19 layers"),
        (GRID, _grid(layers=["elevation", "colour"]), 400, "colour"),
        (GRID, _grid(level="galaxy"), 404, "galaxy"),
        (GRID, _grid(level="\u00b2"), 404, "\u00b2"),
        (SAFETY, _poly([]), 400, "polygon 0 has 0 points"),
        (SAFETY, _poly([(0, 0), (1, 1)]), 400, "polygon 0 has 2 points"),
        (SAFETY, _poly([(0, 0), (1, 1), (2, 2)]), 400, "no area"),
        (SAFETY, _poly([(0, 0), (1, float("nan")), (0, 1)]), 422, "polygon"),
        (SAFETY, _poly(SQUARE, frame="map"), 400, "frame_id 'map'"),
        (SAFETY, _poly([(-1e5, -1e5), (1e5, -1e5), (0, 1e5)]), 413, "1,000,000"),
        (SAFETY, _poly(SQUARE) | {"level": "galaxy"}, 404, "galaxy"),
        (SAFETY, {"polygons": _poly(SQUARE)["polygons"] * 101}, 422, "polygons"),
        (PATH, {"path": {"poses": []}}, 422, "poses"),
        (PATH, {"path": {"header": {"frame_id": "odom"}, "poses": [{}]}}, 400, "path: frame_id"),
        (PATH, {"path": {"poses": [{"header": {"frame_id": "map"}}]}}, 400, "pose 0: frame_id"),
        (PATH, {"path": _path(np.array([[0, 0], [1, float("nan")]]))}, 422, "position"),
        (PATH, {"path": _path(np.zeros((3, 2)), [1.0, 2.0, 1.5])}, 400, "pose 2 stamp"),
        (PATH, {"path": _path(np.zeros((2, 2)), [0.0, 1000.0])}, 413, "600 s"),
        (PATH, {"path": _path(np.zeros((1, 2))), "layer_name": "costs"}, 400, "costs"),
        (PATH, {"path": _path(np.zeros((1, 2))), "footprint": "[[1, 1]]"}, 400, "footprint"),
        (PATH, {"path": _path(np.zeros((1, 2))), "level": "galaxy"}, 400, "galaxy"),
        (PATH, {"path": _path(np.zeros((1, 2))), "max_cost": 300}, 422, "max_cost"),
        # found on the way: a digit int() does not take, a centre beyond any map (were 500s)
        ("/v1/maps/\u00b2?x=0&y=0", None, 404, "\u00b2"),
        ("/v1/attention?level=\u00b2", None, 400, "\u00b2"),
        ("/v1/maps/vehicle?x=1e300&y=0", None, 400, "1e+300"),
    ],
)
def test_bad_ros_requests_get_a_4xx_naming_the_value(served, path, body, code, names) -> None:
    import json
    import urllib.parse

    _, base = served
    got, answer = call(base, urllib.parse.quote(path, safe="/?=&"), body)
    assert got == code, answer
    assert names in json.dumps(answer, ensure_ascii=False)


def test_what_if_and_is_path_valid_answer_while_the_node_lock_is_held(served) -> None:
    """What If, its start, IsPathValid, CheckSafety, GetGridMap and map windows of What If's
    layers read the copy the last cycle published, never the node's lock: with the lock held
    by the test (as a cycle in progress holds it) they answer, from that cycle
    (``cycle_t_ns``), as What If in-process over the KD and the maps of that cycle answers,
    and as the node's levels hold the cells (the node has finished: the KD and the maps are
    the last cycle's)."""

    live, base = served
    cycle = live.snapshot.cycle_t_ns
    assert cycle == live.status.cycle_t_ns >= 0
    me = np.array(_self(base)["position"][:2])
    plans = [
        {"name": f"p{k}", "t_s": [0.0, 5.0], "speed_mps": [3.0, 3.0],
         "curvature_1pm": [0.05 * (k - 2)] * 2}
        for k in range(5)
    ]  # fmt: skip
    points = me + np.stack([np.arange(0.0, 15.0, 1.0), np.zeros(15)], axis=1)
    sampled = ["elevation", "slope", "traversability", "cost"]  # What If's: always copied
    polys = _safety_polygons(me)[:12]
    grid_req = {"position_x": float(me[0]) + 0.13, "position_y": float(me[1]),
                "length_x": 8.0, "length_y": 6.0, "layers": sampled}  # fmt: skip
    with holding_node_lock(live) as held:  # as a cycle in progress holds it
        assert held == cycle
        in_process = live.call(_what_if_reference, plans)
        code, ans = call(base, "/v1/whatif", {"plans": plans, "horizon_s": 5.0, "traces": True})
        code_s, start = call(base, "/v1/whatif/start")
        code_p, path = call(base, PATH, {"path": _path(points)})
        code_g, grid = call(base, GRID, grid_req)
        code_c, safe = call(base, SAFETY, {"polygons": [_polygon(p, 0.5) for p in polys]})
        code_m, win = call(base, f"/v1/maps/vehicle?x={me[0]}&y={me[1]}&half_m=40&layers="
                                 "elevation,cost")  # fmt: skip
        assert live.call(node_lock_held)  # answered with the lock held throughout
    assert code == 200 and code_s == 200 and code_p == 200, (ans, start, path)
    assert code_g == 200 and code_c == 200 and code_m == 200, (grid, safe, win)
    assert ans["cycle_t_ns"] == start["cycle_t_ns"] == path["cycle_t_ns"] == cycle
    assert grid["cycle_t_ns"] == safe["cycle_t_ns"] == win["cycle_t_ns"] == cycle
    want_safe = _reference_safety(live, polys, 0.5, False, "subsystem")
    for key in ("is_safe", "traversability", "why", "known_fraction"):
        assert safe[key] == want_safe[key], key
    # the maps as the last cycle left them
    xy = _grid_centres(grid["map"]).reshape(-1, 2)
    cells = live.call(level_cells, "subsystem", sampled, xy)
    for layer, arr in zip(sampled, grid["map"]["data"], strict=True):
        M = _grid_matrix(arr)
        np.testing.assert_array_equal(M, cells[layer].astype(np.float64).reshape(M.shape))
    rows, cols = np.meshgrid(*(np.arange(n) for n in np.shape(win["values"]["cost"])),
                             indexing="ij")  # fmt: skip
    res, (ox, oy) = win["resolution_m"], win["origin"]
    at = np.stack([ox + (cols.ravel() + 0.5) * res, oy + (rows.ravel() + 0.5) * res], 1)
    vcells = live.call(level_cells, "vehicle", ["elevation", "cost"], at)
    for layer in ("elevation", "cost"):
        got = np.array(win["values"][layer], dtype=np.float64)
        np.testing.assert_array_equal(got.ravel(), vcells[layer].astype(np.float64))
    want = in_process["whatif"]
    assert ans["t0_ns"] == want.t0_ns == start["t0_ns"] == in_process["start"].t0_ns
    assert start["xy"] == in_process["start"].xy.tolist()
    for i, p in enumerate(ans["plans"]):
        tr = p["trace"]
        assert (
            tr["xy"] == want.xy[i].tolist()
            and tr["nearest_entity"] == want.nearest_entity[i].tolist()
        )
        for k in ("traversability", "cost", "elevation", "clearance_m", "unknown_fraction"):
            np.testing.assert_array_equal(np.array(tr[k], dtype=float),
                                          np.where(np.isfinite(getattr(want, k)[i]),
                                                   getattr(want, k)[i], np.nan))  # fmt: skip
        collided = want.collision_entity[i] >= 0
        assert p["collision_entity"] == (int(want.collision_entity[i]) if collided else None)
    # IsPathValid's rollout is What If's over the same cycle
    end_xy = live.call(_path_end_reference, path)
    assert path["end_gap_m"] == float(np.linalg.norm(end_xy - points[path["end_pose_index"] - 1]))


def _what_if_reference(live, plans: list[dict]) -> dict:
    """What If over the node's own KD and maps (the test holds the node's lock: a
    :meth:`wm.serve.LiveNode.call` that does not take it): ``plans`` rolled out for 5 s, and
    the start from the KD."""
    from wm.whatif import ControlPlan, WhatIf

    node = live.node
    wi = WhatIf(node.kd, node.stack, self_id=node.self_id)
    ctl = [ControlPlan(np.array(p["t_s"]), np.array(p["speed_mps"]),
                       np.array(p["curvature_1pm"]), p["name"]) for p in plans]  # fmt: skip
    return {"whatif": wi.simulate(ctl, horizon_s=5.0), "start": wi.start_from_kd()}


def _path_end_reference(live, path: dict) -> np.ndarray:
    """The last position (world xy m) of What If's rollout of IsPathValid's ``plan``, over the
    node's own KD and maps under its lock (a :meth:`wm.serve.LiveNode.call`)."""
    from wm.whatif import WaypointPlan, WhatIf

    with live.lock:
        node = live.node
        wi = WhatIf(node.kd, node.stack, self_id=node.self_id)
        plan = WaypointPlan(np.array(path["plan"]["t_s"]), np.array(path["plan"]["xy"]), "path")
        res = wi.simulate([plan], level=path["level"], horizon_s=path["horizon_s"])
    return res.xy[0, -1]
