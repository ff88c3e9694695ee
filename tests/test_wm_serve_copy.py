"""The copy each cycle of the live node leaves for the server's answers (wm.serve_copy,
wm.serve.CycleSnapshot). Over real HTTP on localhost while a simulated log is replayed: map
windows, GetGridMap, CheckSafety, class-filtered regions, events, the entities of attention and
the plan answer while another thread holds the node's lock (as a cycle in progress holds it),
from the cycle before, exactly as the node's own maps and KD hold them then; earlier layer
names (``z_m2``) are taken. The node runs in a process of its own and in a thread of the
test's. Then the pieces alone: the demand, the layers chosen within the byte
limit, the taxonomy. The log and the request helper are test_wm_serve's."""

from __future__ import annotations

import io
import json
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from serving import MODES, holding_node_lock, node_lock_held, start_live
from serving import served as served_app

pytest.importorskip("fastapi")
uvicorn = pytest.importorskip("uvicorn")

from test_wm_serve import TOKEN, call, log  # noqa: E402, F401  (log: a fixture)

RATE = 0.25  # replay speed: the 6 s log lasts 24 s, so the node still runs through the test
ANSWER_S = 2.0  # the longest an answer may take with the node's lock held elsewhere, s
SUBSYSTEM_CELLS = 256 * 256  # cells of a default level
WHATIF_BYTES = 4 * 4 * SUBSYSTEM_CELLS * 4  # What If's 4 float32 layers of the 4 levels


@pytest.fixture(scope="module", params=MODES)
def running(log: Path, tmp_path_factory, request):  # noqa: F811 (test_wm_serve's fixture)
    """A live node replaying the log at a quarter of real time on its true poses (no odometry
    process to wait for), in a process of its own and in a thread of this one, served on a
    free localhost port."""
    from wm.config import NodeConfig, PoseSource
    from wm.serve import create_app

    kd_path = tmp_path_factory.mktemp("copy-kd") / "live.duckdb"
    config = NodeConfig(pose_source=PoseSource.TRUTH)
    live = start_live(log, kd_path, config, rate=RATE, mode=request.param)
    with served_app(create_app(live, token=TOKEN)) as base:
        yield live, base
    live.stop()


def _get(base: str, path: str, accept: str = "application/json", body: dict | None = None):
    """(status, body bytes, headers, seconds taken) of one request."""
    req = urllib.request.Request(
        base + path,
        data=None if body is None else json.dumps(body).encode(),
        headers={"Accept": accept, "Authorization": f"Bearer {TOKEN}",
                 "Content-Type": "application/json"},
    )  # fmt: skip
    t0 = time.perf_counter()
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, r.read(), dict(r.headers), time.perf_counter() - t0
    except urllib.error.HTTPError as e:
        return e.code, e.read(), dict(e.headers), time.perf_counter() - t0


def _quick(base: str, path: str, body: dict | None = None) -> dict:
    """The JSON answer of a request that must come within :data:`ANSWER_S` with status 200."""
    code, raw, _, took = _get(base, path, body=body)
    assert code == 200, raw[:500]
    assert took < ANSWER_S, (path, took)
    return json.loads(raw)


def _wait(done, what: str, timeout_s: float = 180.0) -> None:
    deadline = time.time() + timeout_s
    while not done():
        assert time.time() < deadline, f"waited {timeout_s} s for {what}"
        time.sleep(0.05)


def _cells(w: dict) -> np.ndarray:
    """Cell-centre world xy (rows*cols, 2) m of a JSON window, row-major."""
    n_r, n_c = w["shape"]
    res, (x0, y0) = w["resolution_m"], w["origin"]
    rows, cols = np.meshgrid(np.arange(n_r), np.arange(n_c), indexing="ij")
    return np.stack([x0 + (cols.ravel() + 0.5) * res, y0 + (rows.ravel() + 0.5) * res], axis=1)


def _classed(live) -> str | None:
    """The most specific class of a level-4 entity other than the vehicle in the newest
    cycle's copy, if there is one."""
    snap = live.snapshot
    if snap is None:
        return None
    c = snap.cols
    for k in np.flatnonzero((c["level"] == 4) & (c["id"] != snap.self_id)):
        if c["class_name"][k] is not None and c["frame"][k] == "world":
            return str(c["class_name"][k])
    return None


def _in_copy(live, extra: set[str]) -> bool:
    """The newest cycle's copy holds the subsystem ``extra`` layers, the events and level 4's
    entities of attention."""
    snap = live.snapshot
    return (
        snap is not None
        and extra <= set(snap.maps.level("subsystem").specs)
        and snap.events is not None
        and 4 in snap.attention
    )


def test_answers_come_from_the_cycle_copy_while_the_node_lock_is_held(running) -> None:
    """Mid-replay: once asked for, the layers, the events and the entities of attention are in
    every cycle's copy. With the node's lock held by the test (the node waits at its next
    cycle; in the node's process when it runs in one) every answer comes within 2 s, says the
    held cycle (the one before the one waiting), and is what the node's levels and KD hold at
    that cycle: map windows (``z_m2`` read as ``z_sq_dev_sum``), GetGridMap, CheckSafety, a
    region filtered by class, events, attention; the plan is taken. After the lock is
    released the answers follow the node."""

    live, base = running
    # 1.5 s of log in: the maps around the vehicle are filled in, objects classed
    _wait(lambda: live.status.cycles >= 15 and _classed(live) is not None, "15 cycles")
    assert not live.status.done, "the replay ended before the test could start"
    me = _quick(base, "/v1/self")["position"]
    x, y = me[0], me[1]
    maps_q = f"/v1/maps/subsystem?x={x}&y={y}&half_m=6&layers=entity_id,z_m2,elevation"
    grid_req = {"position_x": x, "position_y": y, "length_x": 6.0, "length_y": 4.0,
                "layers": ["z_m2", "class_id", "traversability"]}  # fmt: skip
    # the first requests register what they read: the cycles after copy it
    assert _get(base, maps_q)[0] == 200
    assert _get(base, "/v1/grid_map/get_grid_map", body=grid_req)[0] == 200
    assert _get(base, f"/v1/events?t_from_ns=0&t_to_ns={2**62}")[0] == 200
    assert _get(base, "/v1/attention?level=4")[0] == 200
    extra = {"entity_id", "z_sq_dev_sum", "class_id"}
    _wait(lambda: _in_copy(live, extra), "the copy of what was asked")
    # the copy's map bytes: What If's layers and the three asked for (int64, float64, int32)
    extra_bytes = SUBSYSTEM_CELLS * (8 + 8 + 4)
    assert _quick(base, "/v1/status")["snapshot_map_bytes"] == WHATIF_BYTES + extra_bytes

    poly = np.array([x, y]) + np.array([[-3.0, -3.0], [3.0, -3.0], [3.0, 3.0], [-3.0, 3.0]])
    points = [{"x": a, "y": b} for a, b in poly]
    safety = {"polygons": [{"header": {"frame_id": "world"}, "polygon": {"points": points}}]}
    cls = _classed(live)
    root = live.call(_root_class, cls)  # its geometric class: an ancestor
    region_q = f"/v1/entities?x={x}&y={y}&radius_m=200&class={cls}".replace(" ", "%20")
    root_q = f"/v1/entities?x={x}&y={y}&radius_m=200&class={root}"
    # the node waits at its next cycle; the maps and KD are the held cycle's
    with holding_node_lock(live) as held:
        w = _quick(base, maps_q)
        w_new = _quick(base, maps_q.replace("z_m2", "z_sq_dev_sum"))
        code, npy, headers, took = _get(base, maps_q, accept="application/x-npy")
        assert code == 200 and took < ANSWER_S
        grid = _quick(base, "/v1/grid_map/get_grid_map", grid_req)
        safe = _quick(base, "/v1/elevation_mapping/check_safety", safety)
        by_class, by_root = _quick(base, region_q), _quick(base, root_q)
        events = _quick(base, f"/v1/events?t_from_ns=0&t_to_ns={2**62}")
        att = _quick(base, "/v1/attention?level=4")
        told = _quick(base, "/v1/plan", {"xy": [[x, y], [x + 10.0, y]]})
        assert live.call(node_lock_held) and live.snapshot.cycle_t_ns == held
        gxy = _grid_centres(grid["map"])
        want = live.call(_held_reference, x, y, poly, cls, root, held, _cells(w), gxy)

    for ans in (w, w_new, grid, safe, by_class, by_root, events, att, told):
        assert ans["cycle_t_ns"] == held
    for layer in ("entity_id", "z_sq_dev_sum", "elevation"):
        np.testing.assert_array_equal(
            np.array(w["values"][layer], dtype=np.float64).ravel(), want["window"][layer]
        )
    # the earlier name is the current one, said so in the body and a header
    assert w["layers"] == ["entity_id", "z_sq_dev_sum", "elevation"]
    assert w["renamed_layers"] == {"z_m2": "z_sq_dev_sum"} and w_new["renamed_layers"] == {}
    assert w["values"] == w_new["values"]
    arr = np.load(io.BytesIO(npy))
    assert headers["x-map-renamed-layers"] == "z_m2=z_sq_dev_sum"
    assert json.loads(headers["x-map-meta"])["layers"][1] == "z_sq_dev_sum"
    np.testing.assert_array_equal(
        arr[1].ravel(), np.array(w["values"]["z_sq_dev_sum"], dtype=np.float64).ravel()
    )
    assert grid["map"]["layers"] == ["z_sq_dev_sum", "class_id", "traversability"]
    assert grid["renamed_layers"] == {"z_m2": "z_sq_dev_sum"}
    for layer, data in zip(grid["map"]["layers"], grid["map"]["data"], strict=True):
        got = np.array(data["data"], dtype=np.float64)  # None -> NaN
        np.testing.assert_array_equal(got, want["grid"][layer])
    for key in ("is_safe", "traversability", "why", "known_fraction"):
        assert safe[key] == [want["safe"][key]], key
    want_class, want_root = want["class"], want["root"]
    assert [e["entity_id"] for e in by_class["entities"]] == want_class and want_class
    assert [e["entity_id"] for e in by_root["entities"]] == want_root
    assert set(want_class) < set(want_root)  # a class includes its descendants
    assert events["events"] == want["events"] and want["events"]
    assert att["entities"] == want["attention"] and att["node_level"] == "vehicle"
    assert told["points"] == 2 and want["plan_xy"] == [[x, y], [x + 10.0, y]]

    # released: the node runs on and the answers follow it
    _wait(lambda: live.snapshot.cycle_t_ns > held or live.status.done, "the next cycle")
    assert _quick(base, maps_q)["cycle_t_ns"] > held


def _root_class(live, cls: str) -> str:
    """The geometric class ``cls`` descends from (a :meth:`wm.serve.LiveNode.call`)."""
    with live.lock:
        return live.kd.classes.lineage(cls)[-1]


def _held_reference(live, x, y, poly, cls, root, held, w_xy, grid_xy) -> dict:
    """What the node itself holds at the held cycle, read as the endpoints read it under the
    lock (the test holds the lock: a :meth:`wm.serve.LiveNode.call` that does not take it):
    the subsystem level's cells at the window's and the grid's centres, CheckSafety of
    ``poly``, regions by class, events, attention of level 4, the plan."""
    from kd_store import Circle
    from wm import serve_ros as ros
    from wm.serve import _event_json
    from wm.serve_views import attention_entities, find_level

    node, kd = live.node, live.kd
    lvl = node.stack.level("subsystem")
    circle = Circle("world", (x, y), 200.0)
    return {
        "window": {layer: lvl.read(layer, w_xy).astype(np.float64)
                   for layer in ("entity_id", "z_sq_dev_sum", "elevation")},
        "grid": {layer: lvl.read(layer, grid_xy).astype(np.float64)
                 for layer in ("z_sq_dev_sum", "class_id", "traversability")},
        "safe": ros.polygon_safety(
            ros.polygon_window(find_level(node.stack, "subsystem"), poly),
            ros._entity_boxes(ros.node_what_if(node), [poly], held), poly, 0.0, False, held,
        ),
        "class": kd.region(circle, classes=[cls]).tolist(),
        "root": kd.region(circle, classes=[root]).tolist(),
        "events": [_event_json(e) for e in kd.events(0, 2**62)],
        "attention": attention_entities(node, 4, held),
        "plan_xy": node.plan_xy.tolist(),
    }  # fmt: skip


def _grid_centres(m: dict) -> np.ndarray:
    """World xy (size_y * size_x, 2) m of the cells in GridMap ``data`` order (data[j size_x
    + i] is M[i, j]; index (0, 0) at the largest x and y, i along -x, j along -y)."""
    info = m["info"]
    res, p = info["resolution"], info["pose"]["position"]
    col, row = m["data"][0]["layout"]["dim"]
    j, i = np.meshgrid(np.arange(col["size"]), np.arange(row["size"]), indexing="ij")
    cx = p["x"] + 0.5 * info["length_x"] - 0.5 * res - i.ravel() * res
    cy = p["y"] + 0.5 * info["length_y"] - 0.5 * res - j.ravel() * res
    return np.stack([cx, cy], axis=1)


@pytest.mark.parametrize(
    ("path", "body", "names"),
    [
        ("/v1/maps/subsystem?x=0&y=0&layers=elevation,z_m3", None, "z_m3"),
        ("/v1/maps/vehicle?x=0&y=0&layers=z_M2", None, "z_M2"),
        ("/v1/grid_map/get_grid_map",
         {"position_x": 0, "position_y": 0, "length_x": 2, "length_y": 2, "layers": ["z_m3"]},
         "z_m3"),
    ],
)  # fmt: skip
def test_an_unknown_layer_is_a_400_naming_it(running, path, body, names) -> None:
    _, base = running
    code, raw, _, _ = _get(base, path, body=body)
    assert code == 400, raw
    detail = json.loads(raw)["detail"]
    assert names in detail and "z_m2 (now z_sq_dev_sum)" in detail


# --- the pieces alone --------------------------------------------------------------------------


def test_demand_keeps_what_was_asked_lately_newest_first() -> None:
    from wm.serve_copy import ServedDemand, layer_key

    now = [100.0]
    d = ServedDemand(ttl_s=30.0, clock=lambda: now[0])
    a, b = layer_key("subsystem", "cost"), layer_key("vehicle", "entity_id")
    d.ask([a])
    now[0] += 10.0
    d.ask([b])
    assert d.wanted() == [b, a]
    now[0] += 25.0  # a asked 35 s ago, b 25 s ago
    assert d.wanted() == [b]
    d.ask([a])
    assert d.wanted() == [a, b]
    now[0] += 31.0
    assert d.wanted() == []


def test_layers_to_copy_add_what_was_asked_within_the_byte_limit() -> None:
    """What If's layers of its levels always; the asked ones newest first while they fit (a
    smaller one later may still fit); an unknown level or layer is passed over."""
    from maps.level import LevelConfig
    from maps.stack import MapStack, StackConfig
    from wm.serve_copy import copy_levels, layer_key, layers_to_copy, map_bytes
    from wm.whatif import SAMPLED_LAYERS

    stack = MapStack(
        StackConfig(levels=(LevelConfig("fine", 0.5, 16), LevelConfig("coarse", 2.0, 16)))
    )
    wanted = [layer_key("fine", "z_sq_dev_sum"), layer_key("fine", "last_seen_ns"),
              layer_key("coarse", "class_id"), layer_key("galaxy", "cost"),
              layer_key("fine", "colour"), layer_key("fine", "cost"), ("events",)]  # fmt: skip
    cells = 16 * 16
    got = layers_to_copy(stack, {"fine"}, wanted, budget_bytes=cells * (8 + 4))
    # z_sq_dev_sum (float64) fits, last_seen_ns (int64) not, class_id (int32) does
    assert got == {"fine": (*SAMPLED_LAYERS, "z_sq_dev_sum"), "coarse": ("class_id",)}
    copy = copy_levels(stack, got)
    assert [lvl.name for lvl in copy.levels] == ["fine", "coarse"]
    assert map_bytes(copy) == cells * (4 * 4 + 8 + 4)
    fine = stack.level("fine")
    fine.write("z_sq_dev_sum", np.array([[0.2, 0.2]]), 3.0)
    assert copy.level("fine").read("z_sq_dev_sum", np.array([[0.2, 0.2]]))[0] == 0.0  # a copy


def test_the_taxonomy_answers_as_the_class_library_and_is_kept_while_it_does_not_change() -> None:
    from kd_store import ClassKind, ClassLibrary, ClassPrototype, KDError
    from kd_store.frames import Level
    from wm.serve_copy import Taxonomy

    lib = ClassLibrary.default()
    tax = Taxonomy.of(lib)
    for p in lib:
        assert tax.descendants(p.name) == lib.descendants(p.name)
    assert Taxonomy.of(lib, tax) is tax  # unchanged: shared with the cycle before
    lib.add(ClassPrototype("my_cart", ClassKind.SPECIFIC, Level.OBJECT, is_a="object"))
    new = Taxonomy.of(lib, tax)
    assert new is not tax and "my_cart" in new.descendants("object")
    assert "my_cart" not in tax.descendants("object")  # the old copy stays as it was
    with pytest.raises(KDError, match="'galaxy' is not in the class library"):
        new.descendants("galaxy")
