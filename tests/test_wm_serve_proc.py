"""The live node in a process of its own (wm.serve_proc), over real HTTP on localhost (uvicorn):
it answers as the node in a thread answers, for the same log; a node process that dies is an
error in /v1/status and 503s within seconds, never a hang; and the pieces alone (the framed
pickles, the outbox where a newer snapshot replaces one not taken). A flood of posted frames
is in test_wm_ingest (both modes). The log and the request helper are test_wm_serve's."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from serving import acquire_node_lock, served, start_live

pytest.importorskip("fastapi")
pytest.importorskip("uvicorn")

from test_wm_serve import TOKEN, call, log  # noqa: F401  (log: a fixture)

ANSWER_S = 5.0  # the longest an answer may take once the node's process is gone, s


def _answers(live, base: str) -> dict:
    """Everything the API answers of the node's last cycle, by request: the present (the
    cycle's copy), another time (the node itself), a region, SQL, events, a map window (a
    layer not copied, and one copied), attention, What If of ten plans, its start."""
    _, me = call(base, "/v1/self")
    x, y = me["position"][:2]
    _, reg = call(base, "/v1/entities?x_min=-1e4&y_min=-1e4&x_max=1e4&y_max=1e4")
    ids = [e["entity_id"] for e in reg["entities"]]
    plans = [
        {"name": f"p{k}", "t_s": [0.0, 5.0], "speed_mps": [3.0, 3.0],
         "curvature_1pm": [0.02 * (k - 5)] * 2}
        for k in range(10)
    ]  # fmt: skip
    maps_q = f"/v1/maps/subsystem?x={x}&y={y}&half_m=4&layers=elevation,entity_id"
    out = {
        "self": me,
        "region": reg,
        "circle": call(base, f"/v1/entities?x={x}&y={y}&radius_m=40&level=4"),
        "entities": [call(base, f"/v1/entities/{i}") for i in ids],
        "then": [call(base, f"/v1/entities/{i}?t_ns={me['t_ns']}") for i in ids[:10]],
        "base_link": [call(base, f"/v1/entities/{i}?frame=base_link") for i in ids[:10]],
        "sql": call(base, "/v1/sql", {"query": "SELECT id, status FROM entities ORDER BY id"}),
        "events": call(base, f"/v1/events?t_from_ns=0&t_to_ns={2**62}"),
        "map": call(base, maps_q),
        "attention": call(base, "/v1/attention?level=4"),
        "whatif": call(base, "/v1/whatif", {"plans": plans, "horizon_s": 5.0, "traces": True}),
        "start": call(base, "/v1/whatif/start"),
    }
    out["map_copied"] = call(base, maps_q.replace(",entity_id", ""))  # What If's: copied
    return out


def test_a_node_in_its_own_process_answers_as_one_in_a_thread(log, tmp_path) -> None:  # noqa: F811
    """The same log replayed to its end (true poses: no odometry threads whose sums may
    differ in the last bit) by a node in a process of its own and by one in a thread: every
    answer, from the cycle's copy or from the node itself, is the same JSON."""
    from wm.config import NodeConfig, PoseSource
    from wm.serve import create_app

    config = NodeConfig(pose_source=PoseSource.TRUTH)
    got = {}
    for mode in ("process", "thread"):
        live = start_live(log, tmp_path / f"{mode}.duckdb", config, rate=0.0, mode=mode)
        try:
            assert live.wait(600) and not live.status.error, live.status.error
            with served(create_app(live, token=TOKEN)) as base:
                got[mode] = _answers(live, base)
                code, st = call(base, "/v1/status")
            assert code == 200 and st["cycles"] > 10
            if mode == "process":  # the node's figures, measured in its own process
                proc = st["node_process"]
                assert proc["alive"] and proc["pid"] != os.getpid()
                assert proc["snapshots"] >= 1 and proc["transfer_ms"] > 0
                assert st["cycle_ms"] is not None and st["mean_cycle_ms"] > 0
            else:
                assert st["node_process"] is None
        finally:
            live.stop()
    proc, thread = got["process"], got["thread"]
    assert proc["self"]["frame"] == "world" and len(proc["region"]["entities"]) >= 5
    assert proc["whatif"][0] == 200 and len(proc["whatif"][1]["plans"]) == 10
    assert proc["map"][0] == 200 and proc["map_copied"][0] == 200
    elevation = proc["map"][1]["values"]["elevation"]
    assert elevation == proc["map_copied"][1]["values"]["elevation"]
    assert any(code == 200 for code, _ in proc["then"])  # the node's own history
    assert all(code == 200 for code, _ in proc["base_link"])
    assert proc["sql"][0] == 200 and proc["events"][0] == 200 and proc["attention"][0] == 200
    for key in proc:
        assert proc[key] == thread[key], key


def _waiting_lookup(base: str, path: str, out: list) -> None:
    t0 = time.perf_counter()
    code, ans = call(base, path)
    out.append((code, ans, time.perf_counter() - t0))


def test_a_killed_node_process_is_an_error_and_503s_never_a_hang(log, tmp_path) -> None:  # noqa: F811
    """The node's process killed mid-replay (SIGKILL: no last words): within seconds
    /v1/status names the end in ``error``, every answer that needs the node is a 503 (a
    request in flight too), none waits, a stream ends; stopping the node then returns at
    once."""
    from wm.client import Client
    from wm.serve import create_app

    live = start_live(log, tmp_path / "killed.duckdb", rate=1.0, mode="process")
    try:
        with served(create_app(live, token=TOKEN)) as base:
            deadline = time.time() + 120
            while live.status.cycles < 3 and time.time() < deadline:
                time.sleep(0.05)
            assert live.status.cycles >= 3 and not live.status.done
            code, me = call(base, "/v1/self")
            assert code == 200
            events: list = []
            client = Client(base, token=TOKEN)
            reader = threading.Thread(target=lambda: events.extend(client.stream(timeout_s=60)))
            reader.start()
            time.sleep(0.5)  # subscribed (which takes the node's lock once)
            flight: list = []
            # a lookup of another time waits in the node's process for the node's lock, held
            # here as a long cycle would hold it (SQL no longer goes there: wm.serve_sql)
            live.call(acquire_node_lock)
            then = f"/v1/entities/{me['entity_id']}?t_ns={me['t_ns']}"
            slow = threading.Thread(target=_waiting_lookup, args=(base, then, flight))
            slow.start()
            time.sleep(0.5)  # the lookup waits in the node's process
            os.kill(live.process_status()["pid"], signal.SIGKILL)
            t0 = time.perf_counter()
            slow.join(ANSWER_S + 5)
            assert flight and flight[0][0] == 503, flight
            assert "node's process ended" in flight[0][1]["detail"]
            reader.join(ANSWER_S + 5)  # the stream ends too
            assert not reader.is_alive() and events[-1]["event"] == "end", events[-1:]
            st = None
            while time.perf_counter() - t0 < ANSWER_S:
                code, st = call(base, "/v1/status")
                if st["error"]:
                    break
                time.sleep(0.05)
            assert code == 200 and "exit code -9" in st["error"], st
            assert st["node_process"]["alive"] is False
            plan = {"plans": [{"t_s": [0.0, 1.0], "speed_mps": [1.0, 1.0],
                               "curvature_1pm": [0.0, 0.0]}]}  # fmt: skip
            for path, body in [
                ("/v1/self", None),
                (f"/v1/entities/{me['entity_id']}", None),
                (f"/v1/entities/{me['entity_id']}?t_ns={me['t_ns']}", None),
                ("/v1/entities?x=0&y=0&radius_m=50", None),
                (f"/v1/events?t_from_ns=0&t_to_ns={2**62}", None),
                ("/v1/sql", {"query": "SELECT 1"}),
                ("/v1/maps/subsystem?x=0&y=0&half_m=2", None),
                ("/v1/attention?level=4", None),
                ("/v1/whatif", plan),
                ("/v1/whatif/start", None),
                ("/v1/plan", {"xy": [[0.0, 0.0], [1.0, 0.0]]}),
                ("/v1/stream", None),
            ]:
                t = time.perf_counter()
                code, ans = call(base, path, body)
                assert code == 503, (path, code, ans)
                assert time.perf_counter() - t < ANSWER_S, path
        t = time.perf_counter()
        assert live.wait(ANSWER_S) is False  # it never finished the log
    finally:
        live.stop()
    assert time.perf_counter() - t < ANSWER_S


# --- the pieces alone --------------------------------------------------------------------------


def test_a_framed_pickle_crosses_a_pipe_with_its_arrays_whole() -> None:
    """Large arrays go out of band, small ones and objects in band; what arrives equals what
    was sent and its arrays are writable (each in a buffer of its own); a State of the KD and
    a Taxonomy (sent without its class library) cross too."""
    import multiprocessing as mp

    from kd_store.frames import State
    from wm.serve_copy import Taxonomy
    from wm.serve_proc import recv_message, send_message

    big = np.arange(300_000, dtype=np.float32).reshape(300, 1000)
    obj = {
        "big": big, "small": np.arange(5), "empty": np.zeros(0), "names": np.array(["a", None]),
        "state": State(7, "world", (1.0, 2.0, 3.0), velocity_xyz=(4.0, 5.0, 6.0)),
        "taxonomy": Taxonomy({"car": "vehicle", "vehicle": None}, object(), 3),
    }  # fmt: skip
    a, b = mp.Pipe()
    lock = threading.Lock()
    sender = threading.Thread(target=send_message, args=(a, obj, lock))
    sender.start()  # the array is larger than the pipe holds: the reader must run meanwhile
    got = recv_message(b)
    sender.join()
    np.testing.assert_array_equal(got["big"], big)
    assert got["big"].flags.writeable and got["big"].dtype == np.float32
    np.testing.assert_array_equal(got["small"], obj["small"])
    assert got["empty"].shape == (0,) and got["names"].tolist() == ["a", None]
    s = got["state"]
    assert (s.t_ns, s.frame) == (7, "world") and s.velocity_xyz.tolist() == [4.0, 5.0, 6.0]
    with pytest.raises(AttributeError):
        s.t_ns = 8  # still immutable
    t = got["taxonomy"]
    assert t.library is None and t.version == 3 and t.descendants("vehicle") == {"car", "vehicle"}


def test_a_snapshot_not_taken_is_replaced_by_the_newer_and_counted() -> None:
    """The node posts three cycles before the sender takes any: the sender gets the newest
    with the newest status, two are counted replaced; a status alone waits its period, the
    final one does not."""
    from wm.serve import LiveNode, LiveStatus
    from wm.serve_proc import STATUS_PERIOD_S, _Outbox

    class Node:  # what the outbox reads of a LiveNode
        status = LiveStatus()
        snapshot = None

    live: LiveNode = Node()  # type: ignore[assignment]
    box = _Outbox()
    for k in range(3):
        live.status.cycles, live.snapshot = k + 1, f"snapshot {k}"
        box.post(live, fresh=True, final=False)
    news = box.take(0.0, 1.5)
    assert news.snapshot == "snapshot 2" and news.status.cycles == 3 and news.replaced == 2
    assert news.send_ms == 1.5 and not news.final
    live.status.frames = 9
    box.post(live, fresh=False, final=False)  # a status alone, just after a send
    t0 = time.monotonic()
    news = box.take(t0, 0.0)
    assert time.monotonic() - t0 >= 0.9 * STATUS_PERIOD_S
    assert news.snapshot is None and news.status.frames == 9
    box.post(live, fresh=False, final=True)
    t0 = time.monotonic()
    news = box.take(t0, 0.0)
    assert news.final and time.monotonic() - t0 < STATUS_PERIOD_S
    assert box.replaced == 2


def test_news_of_stream_messages_alone_leave_the_status_as_it_was() -> None:
    """A stream message wakes the sender before the node posts a new status: that news
    carries no status, and the server keeps the one it has (it once got an empty one, and
    its cycle count fell to 0 while a client read the stream)."""
    from wm.serve import LiveStatus
    from wm.serve_proc import NodeLink, NodeNews, _Outbox

    class Node:
        status = LiveStatus(cycles=7)
        snapshot = None

    box = _Outbox()
    box.post(Node(), fresh=False, final=True)  # type: ignore[arg-type]
    assert box.take(0.0, 0.0).status.cycles == 7
    box.stream(b"cycle 8")
    news = box.take(time.monotonic(), 0.0)
    assert news.stream == [b"cycle 8"] and news.status is None
    # the server's side installs it: the status stays, the message reaches the stream
    got: list[bytes] = []

    class Live:
        status = LiveStatus(cycles=7)
        snapshot = None
        stream_sink = got.append
        sql_replica = None

    link = NodeLink(Live())  # type: ignore[arg-type]
    link.alive = True
    link._install(NodeNews(None, None, 0.0, [b"cycle 8"]))
    assert link.live.status.cycles == 7 and got == [b"cycle 8"]


def test_a_server_far_behind_gets_a_seed_not_an_ever_longer_outbox() -> None:
    """The replica's deltas wait in the node's outbox while the sender is slow; one more than
    the bound drops them all (counted) and asks the feed for a new seed, which then waits
    alone; a seed posted after it is kept with it, in order."""
    from wm.serve_proc import _Outbox
    from wm.serve_sql import MAX_BEHIND_CYCLES, KDDelta, KDSeed

    box = _Outbox()
    asked: list[int] = []
    box.on_replica_dropped = lambda: asked.append(1)
    seed = KDSeed("kd-1.duckdb", 0, 0)
    box.post_replica(seed)
    for k in range(1, MAX_BEHIND_CYCLES + 1):
        box.post_replica(KDDelta(k, k, None))
    assert not asked and box.replica_dropped == 0
    box.post_replica(KDDelta(MAX_BEHIND_CYCLES + 1, 0, None))
    assert asked == [1] and box.replica_dropped == MAX_BEHIND_CYCLES + 1
    again = KDSeed("kd-2.duckdb", MAX_BEHIND_CYCLES + 1, 0)
    box.post_replica(again)
    news = box.take(0.0, 0.0)
    assert news.replica == [seed, again] and news.replica_dropped == MAX_BEHIND_CYCLES + 1


def test_a_node_that_cannot_start_says_why(log, tmp_path: Path) -> None:  # noqa: F811
    """A KD path the node's process cannot create (below a file): start() raises a
    ServeError naming the cause, as the node in a thread does."""
    from wm.serve import LiveNode, ServeError

    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    for process in (True, False):
        live = LiveNode(log, blocker / "kd.duckdb", process=process)
        with pytest.raises(ServeError, match="could not start: FileExistsError"):
            live.start(60)


def test_the_demand_tells_the_node_of_a_new_view_at_once() -> None:
    """A view asked for the first time, or again after it expired, is told at once (the node's
    next cycle copies it); one asked again while held is not (the list goes with the next
    snapshot's answer instead)."""
    from wm.serve_copy import ServedDemand

    now = [0.0]
    demand = ServedDemand(ttl_s=30.0, clock=lambda: now[0])
    told: list = []
    demand.on_new = lambda: told.append(demand.wanted())
    demand.ask([("a",)])
    demand.ask([("a",)])
    demand.ask([("b",), ("a",)])
    now[0] = 31.0
    demand.ask([("a",)])
    assert told == [[("a",)], [("a",), ("b",)], [("a",)]]
