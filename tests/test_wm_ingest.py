"""Streaming ingest (wm.ingest) and the API's input limits (wm.limits) over real HTTP on
localhost (uvicorn): a simulated log's raw CDR messages posted one by one make the KD a run of
that log makes; a flood is dropped and counted; bad input gets a 4xx naming it."""

from __future__ import annotations

import http.client
import json
import socket
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from serving import MODES, served

pytest.importorskip("fastapi")
uvicorn = pytest.importorskip("uvicorn")

POINTS = "sensor_msgs/msg/PointCloud2"


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("ingest") / "default.mcap"
    return simulate_to_log("default", path, seconds=4.0, seed=46, progress=False)


def _messages(log: Path) -> Iterator[tuple[str, str, bytes, int]]:
    """(topic, msgtype, CDR bytes, log time ns) of every message, in log-time order, as the
    ``mcap`` library reads them (not our reader)."""
    from mcap.reader import make_reader

    with open(log, "rb") as f:
        for schema, channel, msg in make_reader(f).iter_messages(log_time_order=True):
            yield channel.topic, schema.name, bytes(msg.data), int(msg.log_time)


def post(base: str, path: str, body: bytes, ctype: str = "application/octet-stream"):
    """(status, JSON, headers) of one POST."""
    req = urllib.request.Request(base + path, data=body, headers={"Content-Type": ctype})
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            return r.status, json.loads(r.read()), dict(r.headers)
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"null"), dict(e.headers)


def post_expecting(base: str, path: str, body: bytes) -> tuple[int, dict]:
    """(status, JSON) of a POST that asks first (``Expect: 100-continue``), as clients of
    large uploads do: a server that refuses the declared length answers before the body is
    sent. Sending the body regardless races the server closing the connection (a broken pipe
    on a loaded machine)."""
    host, port = base.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=60) as sock:
        head = (f"POST {path} HTTP/1.1\r\nHost: {host}\r\n"
                "Content-Type: application/octet-stream\r\n"
                f"Content-Length: {len(body)}\r\nExpect: 100-continue\r\n\r\n")  # fmt: skip
        sock.sendall(head.encode())
        r = http.client.HTTPResponse(sock)
        r.begin()
        if r.status == 100:  # the server wants the body after all
            sock.sendall(body)
            r = http.client.HTTPResponse(sock)
            r.begin()
        return r.status, json.loads(r.read() or b"null")


def get(base: str, path: str):
    try:
        with urllib.request.urlopen(base + path, timeout=60) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"null")


def ingest_path(topic: str, msgtype: str, t_ns: int) -> str:
    q = urllib.parse.urlencode({"topic": topic, "msgtype": msgtype, "t_ns": t_ns})
    return f"/v1/ingest?{q}"


def _kd_counts(path: Path) -> tuple[int, int, int]:
    """(confirmed entities, all entities, self states) the KD file holds."""
    import duckdb

    with duckdb.connect(str(path), read_only=True) as c:
        return c.sql(
            "SELECT (SELECT count(*) FROM entities WHERE status = 'confirmed'), "
            "(SELECT count(*) FROM entities), (SELECT count(*) FROM entity_states s "
            "JOIN entities e ON s.entity_id = e.id WHERE e.name = 'self')"
        ).fetchall()[0]


def _run_kd(log: Path, kd_path: Path) -> None:
    """The KD of a run of ``log`` (wm.run's loop: every frame to the node, then finish;
    without its scoring, which takes longer than the run)."""
    import kd_store
    from logs import open_log
    from wm.config import NodeConfig
    from wm.node import WorldModelNode
    from wm.tiles import map_stack_over_kd

    with kd_store.open(kd_path) as kd:
        with WorldModelNode(kd, NodeConfig(), map_stack_over_kd(kd)) as node:
            for frame in open_log(log).frames():
                node.feed(frame)


@pytest.mark.parametrize("mode", MODES)
def test_posted_messages_make_the_kd_a_run_makes(log, tmp_path, mode) -> None:
    """Every message of the log posted in log order as raw CDR: the KD the ingesting node
    (in a process of its own, or in a thread) writes has the confirmed entities, entities and
    self states of a run over the log (the same frames reach the same node in the same order:
    an exact match), none dropped."""
    from wm.ingest import IngestNode
    from wm.serve import create_app

    _run_kd(log, tmp_path / "run.duckdb")
    live = IngestNode(tmp_path / "ingest.duckdb", queue_size=10_000, process=mode == "process")
    live.start()
    n = 0
    try:
        with served(create_app(live)) as base:
            for topic, msgtype, data, t_ns in _messages(log):
                code, ans, _ = post(base, ingest_path(topic, msgtype, t_ns), data)
                assert code == 202 and not ans["dropped"], (topic, code, ans)
                n += 1
            code, st = get(base, "/v1/status")
            assert code == 200 and st["log"] is None
            ing = st["ingest"]
            assert ing["messages"] == n and ing["dropped"] == 0 and ing["undecodable"] == 0
    finally:
        live.stop(120)
    assert not live.status.error and live.status.done
    run, ingested = _kd_counts(tmp_path / "run.duckdb"), _kd_counts(tmp_path / "ingest.duckdb")
    assert run[0] > 5 and run[2] > 10
    assert ingested == run


@pytest.fixture(params=MODES)
def ingest_server(tmp_path, request):
    """An ingesting node with a queue of 2 frames and small body limits, in a process of its
    own and in a thread of this one, served."""
    from wm.ingest import IngestNode
    from wm.limits import ServeLimits
    from wm.serve import create_app

    live = IngestNode(":memory:", queue_size=2, process=request.param == "process").start()
    limits = ServeLimits(max_ingest_bytes=2 * 2**20, max_json_bytes=4096)
    with served(create_app(live, limits=limits)) as base:
        yield live, base
    live.stop(60)


def test_a_flood_is_dropped_and_counted(ingest_server, log) -> None:
    """Sweeps posted faster than the node takes them (each cycle slowed to 50 ms): the queue
    never holds more than its 2 frames, the rest are dropped, answered 202 with ``dropped``
    and counted in /v1/status; every frame is either taken or dropped."""
    live, base = ingest_server
    sweep = next(m for m in _messages(log) if m[1] == POINTS)
    live.call(_slow_down, 0.05)
    answers, most_queued = [], 0
    for k in range(40):
        code, ans, _ = post(base, ingest_path(sweep[0], POINTS, 1_000_000_000 + k * 1000), sweep[2])
        assert code == 202
        answers.append(ans)
        most_queued = max(most_queued, live.queue.qsize())
    assert most_queued <= 2
    assert any(a["dropped"] for a in answers)
    code, st = get(base, "/v1/status")
    ing = st["ingest"]
    assert ing["dropped"] > 0 and ing["queue_size"] == 2 and ing["frames"] == 39
    live.end(60)
    assert live.status.frames + live.counts.dropped == live.counts.frames == 40


def _slow_down(live, seconds: float) -> None:
    """Make every feed of the node take ``seconds`` longer (a :meth:`wm.serve.LiveNode.call`:
    in the node's process when it runs in one)."""
    feed = live.node.feed

    def slow_feed(frame):
        time.sleep(seconds)
        return feed(frame)

    live.node.feed = slow_feed


@pytest.mark.parametrize("mode", MODES)
def test_a_flood_of_a_real_log_is_dropped_and_the_node_cycles_on(log, mode) -> None:
    """The log posted to a node (in a process of its own, or in a thread) with a queue of 8
    frames: its first 1.5 s at a pace the node keeps (the client waits for the queue to
    empty), the next second in batches as fast as the client can, then the rest at the node's
    pace again. The flood is dropped and counted (in the answers and in /v1/status) while
    the node takes what it can; the node cycles on through it and after it; every frame is
    taken or dropped."""
    from wm.ingest import IngestNode, pack_batch
    from wm.serve import create_app

    live = IngestNode(":memory:", queue_size=8, process=mode == "process").start()
    msgs = list(_messages(log))
    t0 = msgs[0][3]
    flood_from, flood_to = t0 + 1_500_000_000, t0 + 2_500_000_000

    def paced(part) -> None:
        for topic, msgtype, data, t_ns in part:
            deadline = time.time() + 30
            while live.queue.qsize() and time.time() < deadline:
                time.sleep(0.002)
            code, ans, _ = post(base, ingest_path(topic, msgtype, t_ns), data)
            assert code == 202, ans

    try:
        with served(create_app(live)) as base:
            paced(m for m in msgs if m[3] < flood_from)
            deadline = time.time() + 60
            while live.status.cycles < 5 and time.time() < deadline:
                time.sleep(0.05)
            before = live.status.cycles
            assert before >= 5, live.status
            batches, batch = [], []
            for m in (m for m in msgs if flood_from <= m[3] < flood_to):
                if batch and sum(len(b[2]) for b in batch) + len(m[2]) > 16 * 2**20:
                    batches.append(batch)
                    batch = []
                batch.append(m)
            batches.append(batch)
            dropped = 0
            for part in batches:
                code, ans, _ = post(base, "/v1/ingest/batch", pack_batch(part))
                assert code == 202, ans
                dropped += ans["dropped"]
            code, st = get(base, "/v1/status")
            assert code == 200 and not st["error"]
            assert dropped > 0 and st["ingest"]["dropped"] == dropped == live.counts.dropped
            assert st["ingest"]["queued"] <= 8
            paced(m for m in msgs if m[3] >= flood_to)
    finally:
        live.stop(120)
    assert live.status.done and not live.status.error
    assert live.status.cycles > before + 5 and live.status.cycle_t_ns >= flood_to
    assert live.status.frames + live.counts.dropped == live.counts.frames


def test_bad_messages_get_a_400_naming_them(ingest_server) -> None:
    """Bytes that are not a message of their type, an unknown type, a negative time and a
    missing body get a 4xx naming the value; a known type no frame is made of is ignored."""
    _, base = ingest_server
    code, ans, _ = post(base, ingest_path("/ladar/points", POINTS, 5), b"\x00\x01\x00\x00garbage")
    assert code == 400 and "/ladar/points" in ans["detail"] and POINTS in ans["detail"]
    code, ans, _ = post(base, ingest_path("/x", "no_pkg/msg/Nothing", 5), b"\x00\x01\x00\x00")
    assert code == 400 and "no_pkg/msg/Nothing" in ans["detail"]
    code, ans, _ = post(base, ingest_path("/x", POINTS, -1), b"")
    assert code == 422 and "t_ns" in json.dumps(ans)
    code, ans, _ = post(base, ingest_path("/diag", "std_msgs/msg/String", 5), b"\x00\x01\x00\x00")
    assert code == 202 and ans["ignored"]
    code, st = get(base, "/v1/status")
    assert st["ingest"]["undecodable"] == 1 and st["ingest"]["ignored"] == 1


def test_bodies_above_the_limits_get_a_413(ingest_server) -> None:
    """A body above the ingest limit (declared, or sent chunked without a length) and a JSON
    body above the JSON limit are refused with a 413 naming the size and the limit."""
    _, base = ingest_server
    big = b"\x00" * (2 * 2**20 + 1)
    code, ans = post_expecting(base, ingest_path("/ladar/points", POINTS, 5), big)
    assert code == 413 and str(2 * 2**20) in ans["detail"]
    code, ans, _ = post(
        base, "/v1/sql", json.dumps({"query": "x" * 5000}).encode(), "application/json"
    )
    assert code == 413 and "4096" in ans["detail"]
    # chunked: no Content-Length, the middleware counts what arrives
    host, port = base.removeprefix("http://").split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=30)
    conn.request(
        "POST", ingest_path("/ladar/points", POINTS, 5), body=iter([big[:2**20], big[2**20:]]),
        headers={"Content-Type": "application/octet-stream"}, encode_chunked=True,
    )  # fmt: skip
    r = conn.getresponse()
    assert r.status == 413 and "limit" in json.loads(r.read())["detail"]
    conn.close()


def test_a_client_above_its_rate_gets_a_429(log) -> None:
    """With a rate limit of 1 request per 100 s after a burst of 3 (slow enough that a loaded
    machine cannot refill a token between requests), the fourth request gets a 429 with
    Retry-After; without one (the default) there is no limit."""
    from wm.limits import ServeLimits, TokenBuckets
    from wm.serve import LiveNode, create_app

    live = LiveNode(log, rate=0.0).start()
    try:
        with served(create_app(live, limits=ServeLimits(rate_per_s=0.01, burst=3))) as base:
            codes = [get(base, "/v1/status")[0] for _ in range(4)]
            assert codes == [200, 200, 200, 429]
            req = urllib.request.Request(base + "/v1/status")
            with pytest.raises(urllib.error.HTTPError) as e:
                urllib.request.urlopen(req, timeout=30)
            assert e.value.code == 429 and int(e.value.headers["Retry-After"]) >= 1
        with served(create_app(live)) as base:
            assert all(get(base, "/v1/status")[0] == 200 for _ in range(20))
    finally:
        live.stop()
    buckets = TokenBuckets(rate_per_s=2.0, burst=1, max_clients=2)
    assert buckets.take("a", 0.0) == 0.0 and buckets.take("a", 0.0) == pytest.approx(0.5)
    assert buckets.take("a", 0.5) == 0.0  # refilled
    buckets.take("b", 1.0), buckets.take("c", 1.0)
    assert len(buckets._buckets) == 2  # the least recently seen forgotten


def test_a_batch_is_taken_in_order(ingest_server, log) -> None:
    """A batch of the log's first messages is taken as they would be one by one; a batch with
    a bad message gets a 400 naming it (those before it taken), one cut short a 400 naming
    the byte where."""
    from wm.ingest import pack_batch

    live, base = ingest_server
    msgs = [m for _, m in zip(range(30), _messages(log), strict=False)]
    code, ans, _ = post(base, "/v1/ingest/batch", pack_batch(msgs))
    assert code == 202 and ans["messages"] == 30 and live.counts.messages == 30
    bad = [(*msgs[-1][:3], msgs[-1][3] + 1), ("/ladar/points", POINTS, b"\x00\x01junk", 10**10)]
    code, ans, _ = post(base, "/v1/ingest/batch", pack_batch(bad))
    assert code == 400 and "batch message 1" in ans["detail"] and POINTS in ans["detail"]
    assert live.counts.messages == 31
    code, ans, _ = post(base, "/v1/ingest/batch", pack_batch(msgs[:2])[:-3])
    assert code == 400 and "declares" in ans["detail"] and "at byte" in ans["detail"]
