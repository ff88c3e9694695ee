"""The live node's API under load (wm.serve), on localhost: a 12 s default-scenario log replayed
in real time, once alone (the baseline) and once while a load generator in processes of its own
sends a bounded mix of requests at a fixed rate (entity lookups, circle queries, What If with
10 plans, small SQL).
Figures: p50 / p99 latency per endpoint, the node's mean wall time per cycle under load against
alone, and the staleness of answers (lag of the newest cycle behind the newest frame read).
Targets (the network API's): p99 <= 20 ms for lookups and region queries, <= 60 ms for What
If of 10 plans, cycle time at most 10 % longer under load.

The node runs in a process of its own (``LiveNode(..., process=True)``, as ``wm serve`` runs
it), its cycle time measured there; ``--in-process`` (``python -m bench.bench_serve
--in-process``) runs it in a thread of the server's process instead, as before. Also
recorded: the wall time of a cycle's copy crossing to the server (``transfer_ms``) and the
node process's share of it (``send_ms``)."""

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


def _requests(me: dict, ids: list[int]) -> list[tuple[str, str, str, dict | None]]:
    """The mix: (endpoint name, method, path, body)."""
    x, y = me["position"][:2]
    plans = [
        {"name": f"p{k}", "t_s": [0.0, 5.0], "speed_mps": [3.0, 3.0],
         "curvature_1pm": [0.02 * (k - 5)] * 2}
        for k in range(10)
    ]  # fmt: skip
    mix = [("region", "GET", f"/v1/entities?x={x}&y={y}&radius_m=40&level=4", None)] * 3
    mix += [("self", "GET", "/v1/self", None)] * 3
    mix += [("entity", "GET", f"/v1/entities/{i}", None) for i in ids[:3]]
    mix += [("whatif10", "POST", "/v1/whatif", {"plans": plans, "horizon_s": 5.0})]
    mix += [("sql", "POST", "/v1/sql", {"query": "SELECT count(*) FROM entities"})]
    return mix


def _load(port: int, live, lat: dict[str, list[float]], errors: list[str]) -> None:
    """Send the mix at RATE_PER_S in all until the replay ends (bounded by the log's length),
    from WORKERS processes of their own: the server's process runs only the server (and the
    node), so its figures are not its clients' Python competing for its interpreter lock."""
    import multiprocessing

    c = http.client.HTTPConnection("127.0.0.1", port, timeout=30)

    def call(method: str, path: str, body: dict | None) -> tuple[int, dict]:
        data = None if body is None else json.dumps(body)
        c.request(method, path, body=data, headers={"Content-Type": "application/json"})
        r = c.getresponse()
        return r.status, json.loads(r.read())

    _, me = call("GET", "/v1/self", None)
    _, reg = call("GET", "/v1/entities?x_min=-1e4&y_min=-1e4&x_max=1e4&y_max=1e4&level=4", None)
    mix = _requests(me, [e["entity_id"] for e in reg["entities"]] or [me["entity_id"]])
    c.close()

    # spawn, not fork: the server's process has threads (uvicorn, the node) a fork would copy
    # in whatever state they are in
    ctx = multiprocessing.get_context("spawn")
    stop, results = ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_worker, args=(port, mix, k, stop, results), daemon=True)
             for k in range(WORKERS)]  # fmt: skip
    for p in procs:
        p.start()
    while not live.status.done:
        time.sleep(0.05)
    stop.set()
    for _ in procs:  # before joining: a process ends only once its queue is drained
        got_lat, got_errors = results.get(timeout=120)
        for name, ms in got_lat.items():
            lat.setdefault(name, []).extend(ms)
        errors.extend(got_errors)
    for p in procs:
        p.join(30)


def _worker(port: int, mix: list, k: int, stop: Any, results: Any) -> None:
    """One load process: every WORKERS-th request of ``mix`` from the ``k``-th on, paced at
    RATE_PER_S / WORKERS, until ``stop`` is set; puts (latencies ms by endpoint, errors) on
    ``results``."""
    lat: dict[str, list[float]] = {}
    errors: list[str] = []
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    period = WORKERS / RATE_PER_S
    t_next, n = time.perf_counter(), k
    while not stop.is_set():
        name, method, path, body = mix[n % len(mix)]
        n += WORKERS
        t0 = time.perf_counter()
        try:
            data = None if body is None else json.dumps(body)
            conn.request(method, path, body=data, headers={"Content-Type": "application/json"})
            r = conn.getresponse()
            r.read()
            if r.status >= 500:
                errors.append(f"{name}: HTTP {r.status}")
        except OSError as e:
            errors.append(f"{name}: {e}")
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        lat.setdefault(name, []).append(1e3 * (time.perf_counter() - t0))
        t_next = max(t_next + period, time.perf_counter() - period)  # no catch-up bursts
        time.sleep(max(0.0, t_next - time.perf_counter()))
    conn.close()
    results.put((lat, errors))


def _run(
    log: Path, tmp: Path, loaded: bool, process: bool
) -> tuple[dict, dict[str, list[float]], list[str]]:
    live, srv, thread, port = _serve(log, tmp / f"kd-{loaded}.duckdb", process)
    lat: dict[str, list[float]] = {}
    errors: list[str] = []
    lags: list[int] = []
    while live.status.cycles < 3:
        time.sleep(0.05)
    t0 = time.perf_counter()
    if loaded:
        sampler = threading.Thread(target=_sample_lag, args=(live, lags))
        sampler.start()
        _load(port, live, lat, errors)
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


def main(process: bool = True) -> None:
    from fixtures.simulate import simulate_to_log

    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        log = simulate_to_log("default", tmp / "serve.mcap", seconds=LOG_SECONDS, seed=3,
                              progress=False)  # fmt: skip
        alone, _, _ = _run(log, tmp, loaded=False, process=process)
        loaded, lat, errors = _run(log, tmp, loaded=True, process=process)
    n = sum(len(v) for v in lat.values())
    where = "a process of its own" if process else "a thread of the server's process"
    print(
        f"{n} requests in {loaded['wall_s']:.1f} s (a {LOG_SECONDS:g} s log; alone it took "
        f"{alone['wall_s']:.1f} s), {len(errors)} server errors; the node in {where}"
    )
    print(
        f"mean cycle {alone['mean_cycle_ms']:.1f} ms alone, {loaded['mean_cycle_ms']:.1f} ms "
        f"under load ({loaded['mean_cycle_ms'] / alone['mean_cycle_ms']:.3f}x)"
    )
    for name, ms in sorted(lat.items()):
        p50, p99 = np.percentile(ms, [50, 99])
        print(f"  {name:9s} p50 {p50:6.1f} ms  p99 {p99:6.1f} ms  ({len(ms)} requests)")
    if process:
        print(
            f"copy transfer {loaded['transfer_ms']:.2f} ms mean under load (node's share "
            f"{loaded['send_ms']:.2f} ms), {loaded['replaced']} replaced before taken"
        )
    suffix = "" if process else "_in_process"  # figures of the two modes apart
    targets = {"self": 20.0, "entity": 20.0, "region": 20.0, "whatif10": 60.0, "sql": None}
    for name, ms in sorted(lat.items()):
        a = np.asarray(ms)
        t = targets.get(name)
        record(f"serve_{name}_p50_ms{suffix}", float(np.percentile(a, 50)), "ms", command=CMD)
        record(f"serve_{name}_p99_ms{suffix}", float(np.percentile(a, 99)), "ms",
               target=None if t is None else f"<= {t:g} ms", command=CMD)  # fmt: skip
    record(
        f"serve_cycle_ms_under_load{suffix}", loaded["mean_cycle_ms"], "ms",
        baseline="the same replay with no requests", baseline_value=alone["mean_cycle_ms"],
        target="ratio <= 1.10", command=CMD,
    )  # fmt: skip
    record(f"serve_max_lag_ms_under_load{suffix}", loaded["max_lag_ms"], "ms",
           baseline="no requests", baseline_value=alone["max_lag_ms"], command=CMD)  # fmt: skip
    record(f"serve_requests_per_s{suffix}", n / loaded["wall_s"], "1/s",
           target=f">= {RATE_PER_S:g}", command=CMD)  # fmt: skip
    record(f"serve_replay_wall_s_under_load{suffix}", loaded["wall_s"], "s",
           baseline="the same replay with no requests", baseline_value=alone["wall_s"],
           target="ratio <= 1.0 (real time)", command=CMD)  # fmt: skip
    record(f"serve_server_errors{suffix}", float(len(errors)), "count", target="0", command=CMD)
    if process:
        record("serve_snapshot_transfer_ms_under_load", loaded["transfer_ms"], "ms",
               command=CMD)  # fmt: skip


if __name__ == "__main__":
    import sys

    main(process="--in-process" not in sys.argv[1:])
