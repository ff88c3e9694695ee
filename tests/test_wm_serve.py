"""The live node and its HTTP API (wm.serve) over real HTTP on localhost (uvicorn), fed by a
simulated log replayed at its recorded pace; answers checked against the simulator's truth and
the KD file the node writes."""

from __future__ import annotations

import json
import math
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from serving import MODES, free_port, served, start_live

pytest.importorskip("fastapi")
uvicorn = pytest.importorskip("uvicorn")

TOKEN = "s3cret"


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("serve") / "default.mcap"
    return simulate_to_log("default", path, seconds=6.0, seed=46, progress=False)


@pytest.fixture(scope="module", params=MODES)
def server(log: Path, tmp_path_factory, request):
    """A live node replaying the log at twice real time, in a process of its own and in a
    thread of this one, served on a free localhost port."""
    from wm.serve import create_app

    kd_path = tmp_path_factory.mktemp("serve-kd") / "live.duckdb"
    live = start_live(log, kd_path, rate=2.0, mode=request.param)
    deadline = time.time() + 300  # the tests ask about the vehicle: its first cycle is due
    while live.status.cycles < 1 and not live.status.error and time.time() < deadline:
        time.sleep(0.05)
    assert live.status.cycles >= 1, f"no cycle within 300 s: {live.status}"
    with served(create_app(live, token=TOKEN)) as base:
        yield live, base, kd_path
    live.stop()


def call(base: str, path: str, body: dict | None = None, token: str | None = TOKEN):
    """(status, JSON) of one request."""
    req = urllib.request.Request(
        base + path,
        data=None if body is None else json.dumps(body).encode(),
        headers={"Content-Type": "application/json"}
        | ({"Authorization": f"Bearer {token}"} if token else {}),
    )
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"null")


def wait_status(base: str, done, timeout_s: float) -> dict | None:
    """Poll ``/v1/status`` of a server in another process until ``done(status)`` or the time
    runs out; the last status read (None if it never answered)."""
    deadline, st = time.time() + timeout_s, None
    while time.time() < deadline:
        try:
            code, st = call(base, "/v1/status")
            if code == 200 and done(st):
                break
        except OSError:  # not listening yet
            pass
        time.sleep(0.1)
    return st


def _truth_xy(log: Path, t_ns: int) -> np.ndarray:
    from wm.evaluation import load_truth

    return load_truth(log).poses.at(t_ns)[:3, 3]


def test_answers_come_while_the_node_runs_and_follow_it(server, log) -> None:
    """While the log is replayed the API answers from the newest cycle: the cycle time moves
    on between two answers, the lag behind the newest frame read stays under a second, and
    the self position (odometry, whose world starts at the first pose) moves as the truth
    does."""
    live, base, _ = server
    deadline = time.time() + 60
    while live.status.cycles < 5 and time.time() < deadline:
        time.sleep(0.1)
    code, s1 = call(base, "/v1/self")
    assert code == 200 and s1["frame"] == "world" and not live.status.done
    deadline = time.time() + 120  # a loaded host may run the replay slower than its rate
    while True:
        code, s2 = call(base, "/v1/self")
        assert code == 200
        if s2["t_ns"] - s1["t_ns"] >= 1_000_000_000 or time.time() > deadline:
            break
        time.sleep(0.2)
    assert s2["cycle_t_ns"] > s1["cycle_t_ns"]
    code, st = call(base, "/v1/status")
    assert code == 200 and 0 <= st["lag_ns"] < 1_000_000_000 and st["cycles"] >= 5
    moved = np.linalg.norm(np.subtract(s2["position"], s1["position"]))
    truth = np.linalg.norm(_truth_xy(log, s2["t_ns"]) - _truth_xy(log, s1["t_ns"]))
    assert truth > 2.0 and abs(moved - truth) < 0.1 * truth


def test_region_lookup_and_events_match_the_kd(server) -> None:
    """At the end of the log: every entity a circle query returns lies in the circle and is
    the one the entity lookup and the SQL view give; events have their times in order."""
    live, base, _ = server
    assert live.wait(600) and not live.status.error
    code, me = call(base, "/v1/self")
    assert code == 200
    x, y = me["position"][:2]
    code, reg = call(base, f"/v1/entities?x={x}&y={y}&radius_m=100&level=4&status=confirmed")
    assert code == 200 and reg["frame"] == "world"
    ents = reg["entities"]
    assert len(ents) >= 3
    for e in ents:
        assert math.hypot(e["position"][0] - x, e["position"][1] - y) <= 100.0 + 1e-6
        assert e["status"] == "confirmed"
        code, one = call(base, f"/v1/entities/{e['entity_id']}")
        assert code == 200 and one["position"] == pytest.approx(e["position"])
        # as of its state's time: What Is under the node's lock, not the cycle's copy
        code, then = call(base, f"/v1/entities/{e['entity_id']}?t_ns={e['t_ns']}")
        assert code == 200 and then["position"] == pytest.approx(e["position"])
        assert then["class_name"] == e["class_name"] and then["status"] == e["status"]
    for name in {e["class_name"] for e in ents if e["class_name"]}:
        q = f"/v1/entities?x={x}&y={y}&radius_m=100&level=4&status=confirmed&class={name}"
        code, by_class = call(base, q.replace(" ", "%20"))
        assert code == 200
        assert {e["entity_id"] for e in by_class["entities"]} >= {
            e["entity_id"] for e in ents if e["class_name"] == name
        }
    ids = ",".join(str(e["entity_id"]) for e in ents)
    code, rows = call(base, "/v1/sql", {"query": f"SELECT id FROM entities WHERE id IN ({ids})"})
    assert code == 200 and sorted(r[0] for r in rows["rows"]) == sorted(
        e["entity_id"] for e in ents
    )
    code, under = call(base, "/v1/sql", {"query": "SELECT * FROM range(100_000)"})
    assert code == 200 and len(under["rows"]) == 100_000 and not under["truncated"]
    code, ev = call(base, f"/v1/events?t_from_ns=0&t_to_ns={me['cycle_t_ns']}")
    assert code == 200 and ev["events"]
    starts = [e["t_start_ns"] for e in ev["events"]]
    assert starts == sorted(starts)


@pytest.mark.parametrize(
    ("path", "body", "code", "names"),
    [
        ("/v1/entities/987654321", None, 404, "987654321"),
        ("/v1/self?frame=mars", None, 400, "mars"),
        ("/v1/entities?x=1&y=2", None, 400, "radius_m"),
        ("/v1/entities?x=nan&y=2&radius_m=3", None, 400, "nan"),
        ("/v1/entities?x=0&y=0&radius_m=5&status=happy", None, 400, "happy"),
        ("/v1/entities?x_min=5&y_min=0&x_max=1&y_max=9", None, 400, "x_min < x_max"),
        ("/v1/events?t_from_ns=10&t_to_ns=5", None, 400, "ends before it starts"),
        ("/v1/sql", {"query": "SELECT * FROM read_csv('/etc/passwd')"}, 400, "/etc/passwd"),
        ("/v1/sql", {"query": "COPY entities TO '/tmp/x.csv'"}, 400, "COPY"),
        ("/v1/sql", {"query": "SET enable_external_access = true"}, 400, "SET"),
        ("/v1/sql", {"query": "SELECT 1; DROP TABLE entities"}, 400, "DROP"),
        ("/v1/sql", {"query": "x" * 20_000}, 422, "query"),
        # a result over the row limit: refused as it is read, the limit and query named
        ("/v1/sql", {"query": "SELECT * FROM range(10_000_000)"}, 413, "100,000 rows (max_rows)"),
        ("/v1/sql", {"query": "SELECT * FROM range(10_000_000)"}, 413, "range(10_000_000)"),
    ],
)
def test_bad_requests_get_a_4xx_naming_the_value(server, path, body, code, names) -> None:
    _, base, _ = server
    got, answer = call(base, path, body)
    assert got == code, answer
    assert names in json.dumps(answer)


def test_a_token_is_required_when_set(server) -> None:
    _, base, _ = server
    assert call(base, "/v1/status", token=None)[0] == 401
    assert call(base, "/v1/status", token="wrong")[0] == 401
    assert call(base, "/v1/status")[0] == 200


def test_the_python_client_reads_as_what_is(server) -> None:
    """wm.client answers as the raw API does, and raises ClientError with the server's words."""
    from wm.client import Client, ClientError

    live, base, _ = server
    assert live.wait(600)
    c = Client(base, token=TOKEN)
    me = c.self_state()
    assert me == call(base, "/v1/self")[1]
    x, y = me["position"][:2]
    reg = c.region(x=x, y=y, radius_m=100, levels=[4], statuses=["confirmed"])
    raw = call(base, f"/v1/entities?x={x}&y={y}&radius_m=100&level=4&status=confirmed")[1]
    assert [e["entity_id"] for e in reg["entities"]] == [e["entity_id"] for e in raw["entities"]]
    assert c.sql("SELECT count(*) AS n FROM entities")["rows"][0][0] >= len(reg["entities"])
    with pytest.raises(ClientError, match="987654321") as err:
        c.entity(987654321)
    assert err.value.status == 404
    with pytest.raises(ClientError) as err:
        Client(base).status()
    assert err.value.status == 401


def test_what_if_judges_many_plans_and_says_why(server) -> None:
    """Two plans from the present: stand still, or drive at 3 m/s straight through a
    confirmed object the KD holds. The second collides with that object (its id in the
    answer and in the words of ``why``), carries the collision risk, and is not the best."""
    live, base, _ = server
    assert live.wait(600)
    _, me = call(base, "/v1/self")
    x, y = me["position"][:2]
    _, reg = call(base, f"/v1/entities?x={x}&y={y}&radius_m=40&level=4&status=confirmed")
    objs = [e for e in reg["entities"] if e["entity_id"] != me["entity_id"]]
    assert objs, "no confirmed object within 40 m to drive into"
    target = min(objs, key=lambda e: math.hypot(e["position"][0] - x, e["position"][1] - y))
    tx, ty = target["position"][:2]
    d = math.hypot(tx - x, ty - y)
    beyond = (x + (tx - x) * (d + 5) / d, y + (ty - y) * (d + 5) / d)
    plans = [
        {"name": "stay", "t_s": [0.0, 10.0], "speed_mps": [0.0, 0.0], "curvature_1pm": [0, 0]},
        {"name": "through", "t_s": [0.0, (d + 5) / 3.0], "xy": [[x, y], list(beyond)]},
    ]
    code, ans = call(base, "/v1/whatif", {"plans": plans, "horizon_s": (d + 5) / 3.0})
    assert code == 200, ans
    from wm.client import Client

    assert Client(base, TOKEN).simulate(plans, horizon_s=(d + 5) / 3.0)["plans"] == ans["plans"]
    stay, through = ans["plans"]
    assert stay["collision_entity"] is None and "clear" in stay["why"]
    assert through["collision_entity"] is not None
    assert f"entity {through['collision_entity']}" in through["why"]
    assert through["risk"] > stay["risk"] and ans["best"] == 0


@pytest.mark.parametrize(
    ("plans", "extra", "code", "names"),
    [
        ([{"t_s": [0.0, 2.0, 1.0], "xy": [[0, 0], [1, 0], [2, 0]]}], {}, 400, "t_s[1]=2.0"),
        ([{"t_s": [0.0, 1.0], "xy": [[0, 0], [1, float("nan")]]}], {}, 422, "xy"),
        ([{"t_s": [0.0, 1.0], "xy": [[0, 0], [1, 0]]}], {"level": "galaxy"}, 400, "galaxy"),
        ([{"t_s": [0.0, 1.0]}], {}, 400, "not neither"),
        ([{"t_s": [0.0], "xy": [[0, 0]]}] * 101, {}, 422, "plans"),
        # a place beyond 1e7 m: rollouts and distances would overflow to inf
        ([{"t_s": [0.0, 1.0], "xy": [[0, 0], [1e300, 0]]}], {}, 422, "less than or equal"),
        ([{"t_s": [0.0, 1.0], "xy": [[0, 0], [1, 0]]}], {"goal_xy": [1e300, 0]}, 422, "goal_xy"),
    ],
)
def test_bad_plans_get_a_4xx_naming_the_value(server, plans, extra, code, names) -> None:
    _, base, _ = server
    got, answer = call(base, "/v1/whatif", {"plans": plans, **extra})
    assert got == code, answer
    assert names in json.dumps(answer)


def test_the_kd_file_holds_what_the_api_served(server) -> None:
    """After the node stops, the KD file (written by the live node, flushed as it went) holds
    the confirmed entities the API listed, at the positions it gave."""
    import kd_store

    live, base, kd_path = server
    assert live.wait(600)
    _, me = call(base, "/v1/self")
    x, y = me["position"][:2]
    _, reg = call(base, f"/v1/entities?x={x}&y={y}&radius_m=100&level=4&status=confirmed")
    live.stop()
    assert call(base, "/v1/self")[0] == 503  # stopped: no answers from the last cycle's copy
    with kd_store.open(kd_path, read_only=True) as kd:
        for e in reg["entities"]:
            f = kd.get(e["entity_id"])
            assert f.state.position_xyz == pytest.approx(e["position"])


def test_wm_serve_runs_as_its_own_process_and_stops_cleanly(log, tmp_path) -> None:
    """``wm serve`` in another process, as a controller would meet it: it answers over HTTP
    while replaying, and an interrupt (Ctrl-C) ends it with status 0 and a KD that holds the
    confirmed entities it served."""
    import os
    import signal
    import subprocess
    import sys

    import kd_store

    port = free_port()
    kd_path = tmp_path / "served.duckdb"
    env = os.environ | {"WM_TOKEN": TOKEN}
    cmd = [sys.executable, "-m", "wm.cli", "serve", "--replay", str(log), "--rate", "0",
           "--kd", str(kd_path), "--port", str(port), "--token-env", "WM_TOKEN"]  # fmt: skip
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    base = f"http://127.0.0.1:{port}"
    try:
        st = wait_status(base, lambda s: s["done"], timeout_s=600)
        assert st is not None and st["done"] and not st["error"], st
        _, reg = call(base, "/v1/entities?x_min=-1e4&y_min=-1e4&x_max=1e4&y_max=1e4&level=4")
        confirmed = {e["entity_id"] for e in reg["entities"] if e["status"] == "confirmed"}
        assert len(confirmed) >= 3
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err.decode()[-2000:]
    with kd_store.open(kd_path, read_only=True) as kd:
        stored = kd.sql("SELECT id, status FROM entities").to_pydict()
    held = {i for i, s in zip(stored["id"], stored["status"], strict=True) if s == "confirmed"}
    assert confirmed <= held


def test_sigterm_mid_replay_stops_the_server_with_the_kd_flushed(log, tmp_path) -> None:
    """A service manager stops ``wm serve`` with SIGTERM while it replays: it exits with
    status 0 within seconds, and its KD passes the integrity check and holds every cycle the
    API had reported (the self state of each), as one run."""
    import os
    import signal
    import subprocess
    import sys

    import kd_store
    from kd_store.check import check_file

    port = free_port()
    kd_path = tmp_path / "served.duckdb"
    # a quarter of real time: the 6 s log lasts 24 s, so the replay (which starts before the
    # web server listens) is still going when the test first reaches it on a loaded machine
    # (true poses: the test is of the stop, and an odometry process starting on a machine
    # loaded by other tests can take a minute before the first cycle)
    cmd = [sys.executable, "-m", "wm.cli", "serve", "--replay", str(log), "--rate", "0.25",
           "--poses", "truth", "--kd", str(kd_path), "--port", str(port),
           "--token-env", "WM_TOKEN"]  # fmt: skip
    env = os.environ | {"WM_TOKEN": TOKEN}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    base = f"http://127.0.0.1:{port}"
    try:
        st = wait_status(base, lambda s: s["cycles"] >= 8, timeout_s=120)
        assert st is not None and st["cycles"] >= 8 and not st["done"], st  # mid-replay
        seen = st["cycles"]
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
        stop_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err.decode()[-2000:]
    assert stop_s < 10.0, stop_s
    result = check_file(kd_path)
    assert result.ok, [d.text() for d in result.defects]
    with kd_store.open(kd_path, read_only=True) as kd:
        n_self = kd.sql(
            "SELECT count(*) AS n FROM entity_states s JOIN entities e ON e.id = s.entity_id "
            "WHERE e.name = 'self'"
        )["n"][0].as_py()
        assert kd.sql("SELECT count(*) AS n FROM runs")["n"][0].as_py() == 1
    assert n_self >= seen
