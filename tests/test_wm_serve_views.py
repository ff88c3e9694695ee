"""Map windows, attention and the push stream of the live node (wm.serve_views) over real HTTP
on localhost (uvicorn), against the node's own maps and KD. The log and the request helper
are test_wm_serve's."""

from __future__ import annotations

import io
import json
import math
import socket
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from serving import MODES, level_cells, start_live
from serving import served as served_app

pytest.importorskip("fastapi")
uvicorn = pytest.importorskip("uvicorn")

from test_wm_serve import TOKEN, call, log  # noqa: E402, F401  (log: a fixture)

QUEUE = 3  # cycles a stream client may fall behind: small, so a stalled one drops soon
RATE = 0.4  # replay speed: slow, so the node still runs through the stream test


@pytest.fixture(scope="module", params=MODES)
def served(log: Path, tmp_path_factory, request):  # noqa: F811 (test_wm_serve's fixture)
    """A live node replaying the log at 0.4 times real time (so it is still running while the
    stream test reads), in a process of its own and in a thread of this one, served on a free
    localhost port with a 3-cycle stream queue."""
    from wm.serve import create_app

    kd_path = tmp_path_factory.mktemp("views-kd") / "live.duckdb"
    live = start_live(log, kd_path, rate=RATE, mode=request.param)
    app = create_app(live, token=TOKEN, stream_queue=QUEUE)
    with served_app(app) as base:
        yield live, base, app.state.stream_feed
    live.stop()


def _get(base: str, path: str, accept: str) -> tuple[int, bytes, dict]:
    req = urllib.request.Request(
        base + path, headers={"Accept": accept, "Authorization": f"Bearer {TOKEN}"}
    )
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, r.read(), dict(r.headers)
    except urllib.error.HTTPError as e:
        return e.code, e.read(), dict(e.headers)


def _stalled_reader(base: str) -> socket.socket:
    """A stream client that sends its request and never reads (a tiny receive buffer, so the
    server's writes back up soon)."""
    host, port = base.removeprefix("http://").split(":")
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
    s.connect((host, int(port)))
    s.sendall(
        f"GET /v1/stream HTTP/1.1\r\nHost: {host}\r\nAuthorization: Bearer {TOKEN}\r\n"
        "Accept: text/event-stream\r\n\r\n".encode()
    )
    return s


def _cycles_in(live, seconds: float) -> float:
    """The node's cycles per second of wall time over ``seconds``."""
    c0, t0 = live.status.cycles, time.perf_counter()
    time.sleep(seconds)
    return (live.status.cycles - c0) / (time.perf_counter() - t0)


def _caught_up(live, timeout_s: float = 20.0) -> None:
    """Wait until the node keeps the replay's pace (it starts behind: the odometry process
    and compiled kernels warm up), so two later windows of cycles compare like with like."""
    pace = 10.0 * RATE  # the simulated LADAR sweeps at 10 Hz
    deadline = time.time() + timeout_s
    while _cycles_in(live, 0.5) > 1.3 * pace and time.time() < deadline:
        pass


def _wait_for_clients(c, n: int, timeout_s: float = 10.0) -> None:
    deadline = time.time() + timeout_s
    while c.status()["stream"]["clients"] != n and time.time() < deadline:
        time.sleep(0.05)
    assert c.status()["stream"]["clients"] == n


def test_stream_follows_the_cycles_and_never_slows_the_node(served) -> None:
    """During the replay: a reader sees one message per cycle, in cycle order, whose entities
    the KD holds afterwards; a client that never reads leaves the node's pace as it was and
    gets its missed cycles counted; one that leaves mid-stream is removed, the server fine."""
    from wm.client import Client

    live, base, feed = served
    deadline = time.time() + 60
    while live.status.cycles < 3 and time.time() < deadline:
        time.sleep(0.05)
    assert not live.status.done, "the replay ended before the stream test could start"
    c = Client(base, token=TOKEN)
    got: list[dict] = []
    reader = threading.Thread(target=lambda: got.extend(c.stream(timeout_s=60)), daemon=True)
    reader.start()
    _caught_up(live)
    alone = _cycles_in(live, 2.0)
    # two that never read: over HTTP (the kernel's and the transport's buffers take a few
    # hundred kB first, more than this short log sends) and at the queue itself
    stalled, idle = _stalled_reader(base), feed.subscribe()
    try:
        with_stalled = _cycles_in(live, 2.0)
        _wait_for_clients(c, 3)
        # the paced replay runs as fast with a client that never reads as without one
        assert with_stalled >= 0.6 * alone > 0, (alone, with_stalled)

        leaving = c.stream(timeout_s=60)
        first = next(leaving)
        assert first["event"] == "cycle"
        leaving.close()  # closes the connection mid-stream
        _wait_for_clients(c, 3)

        assert live.wait(600) and not live.status.error
        reader.join(60)
        assert not reader.is_alive()
        # the idle queue kept its newest cycles; the next one it gives says how many went
        dropped = c.status()["stream"]["dropped"]
        assert dropped == idle.dropped > 0
        kept = [idle.take() for _ in range(QUEUE)]
        assert idle.take() is None and [k[1] for k in kept] == [dropped, 0, 0]
        numbers = [json.loads(msg)["cycle"] for msg, _ in kept]
        assert numbers == list(range(feed.published - QUEUE + 1, feed.published + 1))
    finally:
        stalled.close()
        feed.remove(idle)

    cycles = [m for m in got if m["event"] == "cycle"]
    assert got[-1]["event"] == "end" and len(cycles) >= 10
    times = [m["cycle_t_ns"] for m in cycles]
    assert times == sorted(set(times))
    assert all(m["dropped"] == 0 and m["frame"] == "world" for m in cycles)  # it kept up
    assert sum(len(m["created"]) for m in cycles) > 0
    assert any(m["events"] for m in cycles)
    ids = {e["entity_id"] for m in cycles for e in m["created"] + m["changed"]}
    # an entity ends once (denied, gone, or forgotten); the KD may forget an ended one later
    ended = {e["entity_id"] for m in cycles for e in m["ended"]}
    held = set(live.call(_kd_entity_ids))
    stored = {r[0] for r in c.sql("SELECT id FROM entities")["rows"]}
    assert ids - ended <= held | stored and ids & held
    for m in cycles:  # the entity columns are as the KD gave them
        for e in m["created"] + m["changed"]:
            assert e["status"] in ("hypothesized", "confirmed") and len(e["position"]) == 3

    _wait_for_clients(c, 0)  # the stalled one went when it was closed


def _world_of_cells(w: dict) -> np.ndarray:
    """Cell-centre world xy (rows*cols, 2) m of a JSON window, row-major."""
    n_r, n_c = w["shape"]
    res, (x0, y0) = w["resolution_m"], w["origin"]
    rows, cols = np.meshgrid(np.arange(n_r), np.arange(n_c), indexing="ij")
    return np.stack([x0 + (cols.ravel() + 0.5) * res, y0 + (rows.ravel() + 0.5) * res], axis=1)


def test_map_windows_equal_the_node_maps(served) -> None:
    """After the replay (the node paused at its last cycle): JSON, .npy and Arrow windows of
    two levels hold exactly what the node's levels hold at the same cells, including cells
    beyond the level's window (their empty value)."""
    import pyarrow as pa

    live, base, _ = served
    assert live.wait(600)
    _, me = call(base, "/v1/self")
    x, y = me["position"][:2]
    code, w = call(base, f"/v1/maps/subsystem?x={x}&y={y}&half_m=10&layers=elevation,cost")
    assert code == 200, w
    assert w["frame"] == "world" and w["resolution_m"] == 0.4 and w["shape"] == [51, 51]
    assert w["cycle_t_ns"] == live.status.cycle_t_ns
    xy = _world_of_cells(w)
    cells = live.call(level_cells, "subsystem", ["elevation", "cost"], xy)
    for layer in ("elevation", "cost"):
        got = np.array(w["values"][layer], dtype=np.float64).ravel()  # None -> NaN
        np.testing.assert_array_equal(got, cells[layer].astype(np.float64))
    here = live.call(level_cells, "subsystem", ["elevation"], np.array([[x, y]]))
    assert np.isfinite(here["elevation"]).all()

    # a window reaching past the level's own (102 m across) as .npy and as Arrow, level by number
    q = f"/v1/maps/3?x={x}&y={y}&half_m=60&layers=elevation,entity_id,last_seen_ns"
    code, body, headers = _get(base, q, "application/x-npy")
    assert code == 200 and headers["content-type"] == "application/x-npy"
    arr = np.load(io.BytesIO(body))
    meta = json.loads(headers["x-map-meta"])
    assert arr.shape == (3, 301, 301) and headers["x-map-shape"] == "3,301,301"
    assert headers["x-map-frame"] == "world" and meta["layers"] == ["elevation", "entity_id",
                                                                      "last_seen_ns"]  # fmt: skip
    xy = _world_of_cells(meta)
    code, body, _ = _get(base, q, "application/vnd.apache.arrow.stream")
    assert code == 200
    table = pa.ipc.open_stream(body).read_all()
    assert table.column_names == ["row", "col", "x", "y", "elevation", "entity_id", "last_seen_ns"]
    np.testing.assert_allclose(np.c_[table["x"], table["y"]], xy)
    cells = live.call(level_cells, "subsystem", meta["layers"], xy)
    for k, layer in enumerate(meta["layers"]):
        want = cells[layer]
        np.testing.assert_array_equal(arr[k].ravel(), want.astype(np.float64))
        np.testing.assert_array_equal(table[layer].to_numpy(), want)
    assert np.isnan(arr[0, 0, 0]) and arr[1, 0, 0] == -1  # outside the level: empty values


@pytest.mark.parametrize(
    ("query", "accept", "code", "names"),
    [
        ("/v1/maps/galaxy?x=0&y=0", "", 404, "galaxy"),
        ("/v1/maps/7?x=0&y=0", "", 404, "'7'"),
        ("/v1/maps/vehicle?x=0&y=0&layers=elevation,colour", "", 400, "colour"),
        ("/v1/maps/vehicle?x=nan&y=0", "", 400, "nan"),
        ("/v1/maps/vehicle?x=0&y=inf", "", 400, "inf"),
        ("/v1/maps/vehicle?x=0&y=0&half_m=0", "", 400, "half_m 0.0"),
        ("/v1/maps/subsystem?x=0&y=0&half_m=30", "", 413, "10,000"),
        ("/v1/maps/subsystem?x=0&y=0&half_m=300", "application/x-npy", 413, "1,000,000"),
        ("/v1/maps/vehicle?x=0&y=0&half_m=1e300", "application/x-npy", 413, "half_m=1e+300"),
        ("/v1/attention?level=9", "", 400, "'9'"),
        ("/v1/attention?level=galaxy", "", 400, "galaxy"),
    ],
)
def test_bad_views_get_a_4xx_naming_the_value(served, query, accept, code, names) -> None:
    _, base, _ = served
    got, body, _ = _get(base, query, accept or "application/json")
    assert got == code, body
    assert names in json.loads(body)["detail"]


def test_attention_lists_entities_of_the_level_with_why(served) -> None:
    """The level-4 entities of attention: the KD's attention list of the 'vehicle' node level
    in its order first, then SP's tracked entities (their predicted windows); every one of
    level 4, not ended, with a reason; the map level's name asks the same."""
    live, base, _ = served
    assert live.wait(600)
    code, ans = call(base, "/v1/attention?level=4")
    assert code == 200, ans
    assert ans["frame"] == "world" and ans["node_level"] == "vehicle" and ans["entities"]
    assert call(base, "/v1/attention?level=vehicle")[1] == ans
    listed, tracked, positions = live.call(
        _attention_truth, [e["entity_id"] for e in ans["entities"]]
    )
    assert [e["entity_id"] for e in ans["entities"] if e["rank"] is not None] == listed
    for e in ans["entities"]:
        assert e["level"] == 4 and e["status"] in ("confirmed", "hypothesized") and e["why"]
        assert e["position"] == pytest.approx(positions[e["entity_id"]])
        if e["entity_id"] in tracked:
            assert any(w.startswith("predicted window") for w in e["why"])
        if e["status"] == "hypothesized":
            assert "hypothesis awaiting confirmation" in e["why"]
        assert all(math.isfinite(v) for v in e["position"])


def test_a_stream_queue_drops_its_oldest_and_says_how_many() -> None:
    """The bounded queue alone: the put never waits; the next take reports the drops."""
    from wm.serve_views import StreamClient

    q = StreamClient(max_cycles=2)
    for k in range(5):
        q.put(b"%d" % k)
    assert q.take() == (b"3", 3) and q.take() == (b"4", 0) and q.take() is None
    assert q.dropped == 3
    with pytest.raises(ValueError, match="0 cycles"):
        StreamClient(0)


def _kd_entity_ids(live) -> list[int]:
    """The ids the node's KD holds (a :meth:`wm.serve.LiveNode.call`)."""
    with live.lock:
        return live.kd.entity_ids().tolist()


def _attention_truth(live, ids: list[int]) -> tuple[list[int], set[int], dict[int, list]]:
    """(the KD's attention list of the 'vehicle' node level, of level 4 and not ended; SP's
    tracked entities; the KD's current position (world m) of each of ``ids``), under the
    node's lock (a :meth:`wm.serve.LiveNode.call`)."""
    with live.lock:
        kd, node = live.kd, live.node
        listed = [
            i for i in kd.attention("vehicle")
            if int(kd.get(i).level) == 4 and kd.get(i).status.value not in ("denied", "gone")
        ]  # fmt: skip
        tracked = {int(i) for i in node.sp.tracker.tracks.id if i >= 0}
        positions = {i: kd.get(i).state.position_xyz.tolist() for i in ids}
    return [int(i) for i in listed], tracked, positions
