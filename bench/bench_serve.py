"""The live node's API under load (wm.serve), on localhost: a 12 s default-scenario log replayed
in real time, in REPEATS rounds of three replays: alone, while a load generator in processes of
its own sends the network API's mix of requests at a fixed rate (lookups of the vehicle and of
entities by id, circle queries, map windows, What If with 10 plans), and with small SQL added.
Figures: p50 / p99 latency per endpoint, the growth of the node's mean wall time per cycle under
load (round by round against the alone replay of the same round), the server's CPU per
request, the staleness of answers (lag of the newest cycle behind the newest frame read) and of
SQL answers apart (``staleness_ns`` of each, against the newest cycle the server holds: SQL
reads the server's replica of the KD, which each cycle's changes keep current, at most one
cycle behind), and the requests per second sent: the load follows an absolute
schedule (request i due at start + i / rate, a late worker catching up at once), counted over
the time the loaded replay ran from the moment every worker was ready, with how late the sends
were against the schedule (p50, p99), so a generator that falls behind shows as such.
Targets (the network API's): p99 <= 20 ms for lookups and region queries, <= 60 ms for What
If of 10 plans, cycle time at most 10 % longer under the mix, 200 requests/s.

The node runs in a process of its own (``LiveNode(..., process=True)``, as ``wm serve`` runs
it), its cycle time measured there; ``--in-process`` (``python -m bench.bench_serve
--in-process``) runs it in a thread of the server's process instead, as before. Also
recorded: the wall time of a cycle's copy crossing to the server (``transfer_ms``) and the
node process's share of it (``send_ms``), and the replica's cost (the server's apply of a
cycle's changes, ``apply_ms``: the last and the longest; wm.serve_sql)."""

from __future__ import annotations

import http.client
import json
import math
import socket
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.results import record

CMD = "make bench (python -m bench serve)"
LOG_SECONDS = 12.0
RATE_PER_S = 200.0  # requests per second, all workers together
WORKERS = 4
# the most requests the load sends, whatever the replay's pace: the log's length at the rate,
# and as much again for a replay that runs late
MAX_REQUESTS = int(2 * RATE_PER_S * LOG_SECONDS)
# rounds of replays (alone, loaded, loaded with SQL, in turn): a 2-core machine's run-to-run
# spread of the cycle time is as large as the effect measured
REPEATS = 5


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _serve(log: Path, kd: Path, process: bool):
    import uvicorn

    from wm.serve import LiveNode, create_app

    live = LiveNode(log, kd, rate=1.0, process=process).start()
    port = _free_port()
    srv = uvicorn.Server(
        uvicorn.Config(create_app(live), host="127.0.0.1", port=port, log_level="warning")
    )
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    while not srv.started:
        time.sleep(0.02)
    return live, srv, thread, port


def _requests(me: dict, ids: list[int], sql: bool) -> list[tuple[str, str, str, dict | None]]:
    """The mix: (endpoint name, method, path, body): lookups (the vehicle, entities by id),
    circle queries, 20 m map windows of level 2 (JSON) and What If of 10 plans, the load
    the network API's targets are set for; ``sql``: small SQL as well."""
    x, y = me["position"][:2]
    plans = [
        {"name": f"p{k}", "t_s": [0.0, 5.0], "speed_mps": [3.0, 3.0],
         "curvature_1pm": [0.02 * (k - 5)] * 2}
        for k in range(10)
    ]  # fmt: skip
    mix = [("region", "GET", f"/v1/entities?x={x}&y={y}&radius_m=40&level=4", None)] * 3
    mix += [("self", "GET", "/v1/self", None)] * 3
    mix += [("entity", "GET", f"/v1/entities/{i}", None) for i in ids[:3]]
    mix += [("map", "GET", f"/v1/maps/2?x={x}&y={y}&half_m=10&layers=elevation,cost", None)]
    mix += [("whatif10", "POST", "/v1/whatif", {"plans": plans, "horizon_s": 5.0})]
    if sql:
        mix += [("sql", "POST", "/v1/sql", {"query": "SELECT count(*) FROM entities"})]
    return mix


class _Load:
    """WORKERS load processes of their own, started before the server (so they run as any
    client would, not with what the server's process sets for itself, e.g. its CPU
    priority), each waiting for the port and the mix: the server's process runs only the
    server (and the node), so its figures are not its clients' Python competing for its
    interpreter lock."""

    def __init__(self) -> None:
        import multiprocessing

        # spawn, not fork: the bench's process may already have threads a fork would copy in
        # whatever state they are in
        ctx = multiprocessing.get_context("spawn")
        self.stop, self.results, self.ready = ctx.Event(), ctx.Queue(), ctx.Queue()
        self.t_start = ctx.Value("d", math.nan)  # time.monotonic(): one clock for every process
        self.go = [ctx.Queue() for _ in range(WORKERS)]
        self.procs = [
            ctx.Process(target=_worker, args=(k, self.go[k], self.stop, self.results,
                                              self.ready, self.t_start), daemon=True)
            for k in range(WORKERS)
        ]  # fmt: skip
        for p in self.procs:
            p.start()

    def run(
        self, port: int, live, sql: bool, lat: dict[str, list[float]], errors: list[str]
    ) -> dict:
        """Send the mix (with SQL if ``sql``) at RATE_PER_S in all until the replay ends
        (bounded by the log's length). Request i (of all workers) is due at ``t_start + i /
        RATE_PER_S``, an absolute schedule, so a slow answer delays the requests after it but
        does not lower the rate: a worker behind its schedule sends at once until it is on
        time again. ``t_start`` is set once every worker is ready (imports done, connected),
        so start-up is not counted as time sending. Returns the load's figures: requests sent
        while the replay ran, over that time (``achieved_per_s``), how late the sends were
        against the schedule (``late_ms_p50``, ``late_ms_p99``) and the SQL answers'
        staleness (``sql_staleness_ms``, one per answer)."""
        c = http.client.HTTPConnection("127.0.0.1", port, timeout=30)

        def call(method: str, path: str, body: dict | None) -> tuple[int, dict]:
            data = None if body is None else json.dumps(body)
            c.request(method, path, body=data, headers={"Content-Type": "application/json"})
            r = c.getresponse()
            return r.status, json.loads(r.read())

        _, me = call("GET", "/v1/self", None)
        everywhere = "x_min=-1e4&y_min=-1e4&x_max=1e4&y_max=1e4&level=4"
        _, reg = call("GET", f"/v1/entities?{everywhere}", None)
        ids = [e["entity_id"] for e in reg["entities"]] or [me["entity_id"]]
        mix = _requests(me, ids, sql)
        if sql:
            # until the server's replica of the KD, seeded once SQL is asked for, is open (a
            # few tenths of a second) the node answers SQL itself, as of its last flush; the
            # load starts once the replica answers
            body = next(body for name, _, _, body in mix if name == "sql")
            deadline = time.monotonic() + 60
            call("POST", "/v1/sql", body)
            while live.sql_status().get("cycle_t_ns") is None and time.monotonic() < deadline:
                time.sleep(0.1)
        c.close()

        for go in self.go:
            go.put((port, mix))
        for _ in self.procs:
            self.ready.get(timeout=120)
        self.t_start.value = time.monotonic() + 0.05
        time.sleep(max(0.0, self.t_start.value - time.monotonic()))
        cpu0 = time.process_time()  # the server's process: the server (and the bench's waits)
        while not live.status.done:
            time.sleep(0.05)
        t_stop = time.monotonic()
        server_cpu_s = time.process_time() - cpu0
        self.stop.set()
        sent: list[float] = []
        late: list[float] = []
        stale: list[float] = []
        for _ in self.procs:  # before joining: a process ends only once its queue is drained
            got_lat, got_errors, got_sent, got_late, got_stale = self.results.get(timeout=120)
            for name, ms in got_lat.items():
                lat.setdefault(name, []).extend(ms)
            errors.extend(got_errors)
            sent += got_sent
            late += got_late
            stale += got_stale
        for p in self.procs:
            p.join(30)
        window = t_stop - self.t_start.value
        in_window = sum(1 for t in sent if t <= t_stop)
        return {
            "achieved_per_s": in_window / window if window > 0 else math.nan,
            "window_s": window,
            "sent": len(sent),
            "late_ms_p50": float(np.percentile(late, 50)) if late else math.nan,
            "late_ms_p99": float(np.percentile(late, 99)) if late else math.nan,
            "sql_staleness_ms": stale,
            "server_cpu_ms_per_request": 1e3 * server_cpu_s / max(in_window, 1),
            "server_cores": server_cpu_s / window if window > 0 else math.nan,
        }


def _worker(k: int, go: Any, stop: Any, results: Any, ready: Any, t_start: Any) -> None:
    """One load process: waits for (port, mix) on ``go``, then sends requests k, k +
    WORKERS, k + 2 WORKERS, ... of ``mix`` (cycled), request i at ``t_start + i /
    RATE_PER_S`` (time.monotonic(), s; set by the parent once every worker put its name on
    ``ready``), or at once when behind, until ``stop`` is set or :data:`MAX_REQUESTS` are
    due; puts (latencies ms by endpoint, errors, send times, lateness of each send ms,
    staleness of each SQL answer ms) on ``results``."""
    port, mix = go.get()
    lat: dict[str, list[float]] = {}
    errors: list[str] = []
    sent: list[float] = []
    late: list[float] = []
    stale: list[float] = []
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    conn.connect()
    ready.put(k)
    while math.isnan(t_start.value) and not stop.is_set():
        time.sleep(0.005)
    t0 = t_start.value
    for i in range(k, MAX_REQUESTS, WORKERS):
        due = t0 + i / RATE_PER_S
        ahead = due - time.monotonic()
        if ahead > 0 and stop.wait(ahead):
            break
        if stop.is_set():
            break
        name, method, path, body = mix[i % len(mix)]
        t = time.monotonic()
        sent.append(t)
        late.append(1e3 * max(0.0, t - due))
        try:
            data = None if body is None else json.dumps(body)
            conn.request(method, path, body=data, headers={"Content-Type": "application/json"})
            r = conn.getresponse()
            raw = r.read()
            if r.status >= 500:
                errors.append(f"{name}: HTTP {r.status}")
            elif name == "sql":
                staleness = json.loads(raw).get("staleness_ns")
                if staleness is not None:
                    stale.append(staleness / 1e6)
        except OSError as e:
            errors.append(f"{name}: {e}")
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        lat.setdefault(name, []).append(1e3 * (time.monotonic() - t))
    conn.close()
    results.put((lat, errors, sent, late, stale))


def _run(
    log: Path, tmp: Path, load: str, process: bool
) -> tuple[dict, dict[str, list[float]], list[str]]:
    """One replay of ``log``: ``load`` "none" (alone), "api" (the mix) or "sql" (the mix
    and SQL)."""
    workers = _Load() if load != "none" else None
    live, srv, thread, port = _serve(log, tmp / f"kd-{load}.duckdb", process)
    import os as _os

    _n = int(_os.environ.get("WM_API_NICE", "0"))
    for tid in _os.listdir("/proc/self/task"):
        _os.setpriority(_os.PRIO_PROCESS, int(tid), _n)
    lat: dict[str, list[float]] = {}
    errors: list[str] = []
    lags: list[int] = []
    figures: dict = {}
    while live.status.cycles < 3:
        time.sleep(0.05)
    t0 = time.perf_counter()
    if workers is not None:
        sampler = threading.Thread(target=_sample_lag, args=(live, lags))
        sampler.start()
        figures = workers.run(port, live, load == "sql", lat, errors)
        sampler.join()
    else:
        _sample_lag(live, lags)
    # the node's own figures: in its process when it runs in one (LiveStatus crosses with
    # every cycle's copy)
    proc = live.process_status() or {}
    status = {
        "mean_cycle_ms": 1e3 * live.status.feed_s / max(live.status.cycles, 1),
        "max_lag_ms": max(lags) / 1e6 if lags else math.nan,
        "wall_s": time.perf_counter() - t0,
        "transfer_ms": proc.get("mean_transfer_ms") or math.nan,
        "send_ms": proc.get("send_ms") or math.nan,
        "replaced": proc.get("replaced", 0),
        "load": figures,
        "sql": live.sql_status(),
    }
    srv.should_exit = True
    thread.join(10)
    live.stop()
    return status, lat, errors


def _sample_lag(live, lags: list[int]) -> None:
    while not live.status.done:
        s = live.status
        if s.cycle_t_ns >= 0:
            lags.append(s.newest_frame_t_ns - s.cycle_t_ns)
        time.sleep(0.05)


def _report(
    label: str, run: dict, alone: dict, growth: list[float], lat: dict, errors: list, process: bool
) -> None:
    n = sum(len(v) for v in lat.values())
    load = run["load"]
    where = "a process of its own" if process else "a thread of the server's process"
    print(
        f"{label}: {n} requests in {run['wall_s']:.1f} s (a {LOG_SECONDS:g} s log; alone it "
        f"took {alone['wall_s']:.1f} s), {len(errors)} server errors; the node in {where}"
    )
    print(
        f"  load: {load['achieved_per_s']:.1f} requests/s sent over the {load['window_s']:.1f}"
        f" s the replay ran (scheduled {RATE_PER_S:g}/s); sends late against the schedule by "
        f"{load['late_ms_p50']:.1f} ms p50, {load['late_ms_p99']:.1f} ms p99; the server's "
        f"process used {load['server_cpu_ms_per_request']:.2f} ms of CPU a request "
        f"({load['server_cores']:.2f} cores)"
    )
    stale = load["sql_staleness_ms"]
    if stale:
        sql = run["sql"]
        print(
            f"  SQL staleness (newest cycle - the cycle SQL read): "
            f"{np.percentile(stale, 50):.0f} ms p50, {max(stale):.0f} ms max; source "
            f"{sql.get('source')}, {sql.get('seeds_opened')} seed(s) (node's copy "
            f"{sql.get('copy_ms')} ms, server's open {sql.get('open_ms')} ms), "
            f"{sql.get('deltas_applied')} cycles' changes applied (last {sql.get('apply_ms')} "
            f"ms, longest {sql.get('apply_ms_max')} ms), {sql.get('deltas_dropped')} dropped"
        )
    print(
        f"  mean cycle {alone['mean_cycle_ms']:.1f} ms alone, {run['mean_cycle_ms']:.1f} ms "
        f"under load (median runs); growth round by round "
        + ", ".join(f"{g:.3f}" for g in growth)
        + f", median {np.median(growth):.3f}x"
    )
    for name, ms in sorted(lat.items()):
        p50, p99 = np.percentile(ms, [50, 99])
        print(f"  {name:9s} p50 {p50:6.1f} ms  p99 {p99:6.1f} ms  ({len(ms)} requests)")
    if process:
        print(
            f"  copy transfer {run['transfer_ms']:.2f} ms mean under load (node's share "
            f"{run['send_ms']:.2f} ms), {run['replaced']} replaced before taken"
        )


def _median_run(runs: list[dict]) -> dict:
    """The run of the median cycle time (of an odd count; the lower middle otherwise)."""
    ordered = sorted(runs, key=lambda r: r["mean_cycle_ms"])
    return ordered[(len(ordered) - 1) // 2]


def main(process: bool = True) -> None:
    """Replays of one log, REPEATS rounds of three in turn: alone, under the API's mix, and
    under the mix with SQL. The cycle's growth under load is the median over rounds of the
    loaded replay's cycle time over the alone one's of the same round; every other figure of
    a kind of replay is that of its median run (by cycle time), the latencies those of every
    request of its runs."""
    from fixtures.simulate import simulate_to_log

    runs: dict[str, list[dict]] = {"none": [], "api": [], "sql": []}
    lats: dict[str, dict[str, list[float]]] = {"api": {}, "sql": {}}
    errs: dict[str, list[str]] = {"api": [], "sql": []}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        log = simulate_to_log("default", tmp / "serve.mcap", seconds=LOG_SECONDS, seed=3,
                              progress=False)  # fmt: skip
        for _ in range(REPEATS):
            for load in runs:
                status, lat, errors = _run(log, tmp, load, process)
                runs[load].append(status)
                for name, ms in lat.items():
                    lats.get(load, {}).setdefault(name, []).extend(ms)
                errs.get(load, []).extend(errors)
    for load, rs in runs.items():
        print(f"cycle ms, {load}: " + ", ".join(f"{r['mean_cycle_ms']:.1f}" for r in rs))
    # a round's loaded replay against the alone one just before it: the machine's pace drifts
    # over minutes (alone 44 -> 53 ms within one bench), which pairing takes out
    growth = {
        load: [
            r["mean_cycle_ms"] / a["mean_cycle_ms"]
            for r, a in zip(runs[load], runs["none"], strict=True)
        ]
        for load in ("api", "sql")
    }
    alone, loaded, with_sql = (_median_run(runs[k]) for k in ("none", "api", "sql"))
    lat, lat_sql, errors, errors_sql = lats["api"], lats["sql"], errs["api"], errs["sql"]
    _report("the API's mix", loaded, alone, growth["api"], lat, errors, process)
    _report("the mix and SQL", with_sql, alone, growth["sql"], lat_sql, errors_sql, process)

    suffix = "" if process else "_in_process"  # figures of the two modes apart
    targets = {"self": 20.0, "entity": 20.0, "region": 20.0, "whatif10": 60.0}
    for name, ms in sorted({**lat, "sql": lat_sql.get("sql", [])}.items()):
        if not ms:
            continue
        a = np.asarray(ms)
        t = targets.get(name)
        record(f"serve_{name}_p50_ms{suffix}", float(np.percentile(a, 50)), "ms", command=CMD)
        record(f"serve_{name}_p99_ms{suffix}", float(np.percentile(a, 99)), "ms",
               target=None if t is None else f"<= {t:g} ms", command=CMD)  # fmt: skip
    # the growth is taken round by round (above), not as a ratio of these median runs
    record(f"serve_cycle_ms_alone{suffix}", alone["mean_cycle_ms"], "ms", command=CMD)
    for load, name, run in (("api", "", loaded), ("sql", "_with_sql", with_sql)):
        record(f"serve_cycle_ms_under_load{name}{suffix}", run["mean_cycle_ms"], "ms",
               command=CMD)  # fmt: skip
        record(
            f"serve_cycle_growth_under_load{name}{suffix}", float(np.median(growth[load])),
            "ratio", baseline="median over rounds of loaded / alone cycle time, same round",
            target="<= 1.10", command=CMD,
        )  # fmt: skip
        cpu = [r["load"]["server_cpu_ms_per_request"] for r in runs[load]]
        record(f"serve_server_cpu_ms_per_request{name}{suffix}", float(np.median(cpu)), "ms",
               command=CMD)  # fmt: skip
    load = loaded["load"]
    record(f"serve_max_lag_ms_under_load{suffix}", loaded["max_lag_ms"], "ms",
           baseline="no requests", baseline_value=alone["max_lag_ms"], command=CMD)  # fmt: skip
    record(f"serve_requests_per_s{suffix}", load["achieved_per_s"], "1/s",
           target=f">= {RATE_PER_S:g}", command=CMD)  # fmt: skip
    record(f"serve_load_late_ms_p99{suffix}", load["late_ms_p99"], "ms", command=CMD)
    stale = with_sql["load"]["sql_staleness_ms"]
    if stale:
        record(f"serve_sql_staleness_ms_p50{suffix}", float(np.percentile(stale, 50)), "ms",
               command=CMD)  # fmt: skip
        record(f"serve_sql_staleness_ms_max{suffix}", float(max(stale)), "ms", command=CMD)
    record(f"serve_replay_wall_s_under_load{suffix}", loaded["wall_s"], "s",
           baseline="the same replay with no requests", baseline_value=alone["wall_s"],
           target="ratio <= 1.0 (real time)", command=CMD)  # fmt: skip
    record(f"serve_server_errors{suffix}", float(len(errors) + len(errors_sql)), "count",
           target="0", command=CMD)  # fmt: skip
    if process:
        record("serve_snapshot_transfer_ms_under_load", loaded["transfer_ms"], "ms",
               command=CMD)  # fmt: skip


if __name__ == "__main__":
    import sys

    main(process="--in-process" not in sys.argv[1:])
