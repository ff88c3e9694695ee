"""Behavior generation out of process (wm.remote, ``python -m wm.bg``): a planner in a process of
its own plans over the live node's HTTP API (real uvicorn on localhost) while the node replays a
simulated log, and its paths are checked against the simulator's true objects; in-process and
over HTTP the planner picks the same plan for the same cycle.

The node runs on the log's true poses (``PoseSource.TRUTH``), so its world frame is the
simulator's (checked: the planner's start lies on the true pose) and the goal, true objects and
planned paths are compared in one frame, world metres."""

from __future__ import annotations

import io
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from serving import served, start_live

pytest.importorskip("fastapi")
pytest.importorskip("uvicorn")

REPO = Path(__file__).resolve().parents[1]
TOKEN = "bg-s3cret"
SECONDS = 6.0


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("bg-remote") / "default.mcap"
    return simulate_to_log("default", path, seconds=SECONDS, seed=46, progress=False)


@pytest.fixture(scope="module")
def truth(log: Path):
    from wm.evaluation import load_truth

    return load_truth(log)


@pytest.fixture(scope="module")
def server(log: Path):
    """A live node in a process of its own replaying the log at real time on its true poses,
    served on localhost."""
    from wm.config import NodeConfig, PoseSource
    from wm.serve import create_app

    live = start_live(log, ":memory:", NodeConfig(pose_source=PoseSource.TRUTH), rate=1.0)
    with served(create_app(live, token=TOKEN)) as base:
        yield live, base
    live.stop()


def _goal_beyond_an_object(truth) -> tuple[np.ndarray, int]:
    """A goal (world m) 20 m beyond the static true object nearest the vehicle half-way
    through the log, on the line from the vehicle through it: the way straight to the goal
    runs through that object. Returns (goal, the object's truth id)."""
    t = int(SECONDS / 2 * 1e9)
    p = truth.poses.at(t)[:2, 3]
    boxes = truth.boxes[int(np.argmin(np.abs(truth.box_t_ns - t)))]
    static = np.linalg.norm(np.nan_to_num(boxes.velocities), axis=1) < 0.05
    d = np.where(static, np.linalg.norm(boxes.centers[:, :2] - p, axis=1), np.inf)
    k = int(np.argmin(d))
    assert d[k] < 45.0, f"no static true object within 45 m of the vehicle at {p}"
    c = boxes.centers[k, :2]
    return c + 20.0 * (c - p) / d[k], int(boxes.ids[k])


def _true_boxes_at(truth, t_ns: int):
    """(centres (M, 2), sizes (M, 2) length x width, yaws (M,)) of the true objects at
    ``t_ns`` (world m, rad): the nearest truth set moved at its true velocities; past the end
    of the truth, the last set's static objects (the moving ones are not known there)."""
    from wm.evaluation import EvalConfig, truth_at

    got = truth_at(truth, t_ns, EvalConfig())
    if got is not None:
        boxes, centres = got
        return centres[:, :2], boxes.sizes[:, :2], boxes.yaws
    last = truth.boxes[-1]
    static = np.linalg.norm(np.nan_to_num(last.velocities), axis=1) < 0.05
    return last.centers[static, :2], last.sizes[static, :2], last.yaws[static]


def _run_bg(base: str, *args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess:
    env = os.environ | {"PYTHONPATH": str(REPO), "WM_BG_TOKEN": TOKEN}
    cmd = [sys.executable, "-m", "wm.bg", "--url", base, "--token-env", "WM_BG_TOKEN", *args]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout_s)


def test_a_bg_process_plans_over_http_and_never_passes_a_true_object(server, truth) -> None:
    """``python -m wm.bg`` in its own process, while the node replays the log: at least three
    plans, each from a cycle of its own (its What If answers from that cycle or later), and
    none of the chosen paths passes within the vehicle's half-width of a true object at the
    matching times, though the goal lies behind one. The node was told the last path."""
    from core.geometry import footprint_distance
    from wm.config import VehicleConfig

    live, base = server
    goal, target = _goal_beyond_an_object(truth)
    # a clearance of 1.5 m from perceived objects, not the default 0.5: here perception
    # makes a tree's true 2.0 m width 1.2 m, and paths 0.5 m from the perceived box then
    # pass about 1.1 m from the true one (once in a few runs under the 1 m half-width)
    run = _run_bg(base, f"--goal={goal[0]},{goal[1]}", "--cycles", "6", "--json",
                  "--min-clearance-m", "1.5")  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    plans = [json.loads(line) for line in run.stdout.splitlines()]
    assert len(plans) >= 3, run.stdout + run.stderr
    cycles = [p["cycle_t_ns"] for p in plans]
    assert len(set(cycles)) == len(cycles) and cycles == sorted(cycles)
    for p in plans:
        assert p["answer_cycles_t_ns"] and min(p["answer_cycles_t_ns"]) >= p["cycle_t_ns"]
    half_width = 0.5 * VehicleConfig().width_m
    blocked = 0  # plans whose straight way to the goal runs through the target object
    for p in plans:
        start, t0 = np.array(p["start"]["xy"]), p["t0_ns"]
        # the node's world is the truth's: its start is where the vehicle truly was
        assert np.linalg.norm(start - truth.poses.at(t0)[:2, 3]) < 0.05
        xy, t_s = np.array(p["xy"]), np.array(p["t_s"])
        assert xy.shape == (len(t_s), 2) and np.allclose(xy[0], start)
        assert p["collision_entity"] is None
        for point, t in zip(xy, t_s, strict=True):
            c, size, yaw = _true_boxes_at(truth, t0 + round(t * 1e9))
            d = footprint_distance(point[None], c, size, yaw)[:, 0]
            k = int(np.argmin(d))
            assert d[k] > half_width, (
                f"plan {p['plan']} from t0_ns={t0} passes {d[k]:.2f} m from a true object "
                f"at {c[k].round(1).tolist()} at t={t:.1f} s"
            )
        boxes = truth.boxes[-1]
        k = int(np.flatnonzero(boxes.ids == target)[0])
        line = start + np.linspace(0.0, 1.0, 200)[:, None] * (goal - start)
        d = footprint_distance(line, boxes.centers[k : k + 1, :2], boxes.sizes[k : k + 1, :2],
                               boxes.yaws[k : k + 1])  # fmt: skip
        blocked += bool(d.min() <= half_width)
    assert blocked >= 1, "the goal was never behind the target object: the check proves little"
    moved = max(np.linalg.norm(np.subtract(p["xy"][-1], p["xy"][0])) for p in plans)
    assert moved > 5.0, "every plan stood still: avoiding objects that way proves nothing"
    told = live.call(_node_plan)
    assert told is not None and np.array_equal(told, np.array(plans[-1]["xy"]))


def test_in_process_and_remote_planners_pick_the_same_plan(server) -> None:
    """After the replay: Planner over the node's own What If and Planner over the API, from
    the same start towards the same goal, choose the same plan with the same cost and path;
    the BG loop plans once over the last cycle, prints it in one line, and ends."""
    from wm.bg import Planner
    from wm.client import Client
    from wm.config import PlannerConfig
    from wm.remote import RemoteWhatIf, run_bg

    live, base = server
    assert live.wait(120) and not live.status.error
    cfg = PlannerConfig(budget_s=60.0)  # every candidate weighed on both sides
    start, goal, here = live.call(_plan_in_process, cfg)
    remote = RemoteWhatIf(Client(base, TOKEN))
    far = Planner(remote, cfg).plan(goal)  # its start through the API
    assert remote.start_cycle_t_ns == live.status.cycle_t_ns
    assert far.t_s.tolist() == here.t_s.tolist() and np.array_equal(far.xy[0], start.xy)
    assert far.n_candidates == here.n_candidates and not far.budget_hit
    assert far.index == here.index and far.plan.name == here.plan.name
    assert abs(far.cost - here.cost) < 1e-9 and abs(far.risk - here.risk) < 1e-9
    np.testing.assert_allclose(far.xy, here.xy, atol=1e-9)
    # the process's loop on a finished node: one plan over the last cycle, then it ends
    out = io.StringIO()
    made = run_bg(Client(base, TOKEN), goal, cfg, cycles=None, tell=False, out=out)
    line = out.getvalue().strip()
    assert made == 1 and len(line.splitlines()) == 1, line
    assert f"t0_ns={start.t0_ns} cycle_t_ns={live.status.cycle_t_ns} plan={here.plan.name} " in line
    assert f" cost={here.cost:.3f} risk={here.risk:.3f} collision=none elapsed_ms=" in line


def _node_plan(live) -> np.ndarray | None:
    """The plan the node was told (a :meth:`wm.serve.LiveNode.call`)."""
    return live.node.plan_xy


def _plan_in_process(live, cfg) -> tuple:
    """(start, goal, plan) of Planner over the node's own What If, towards a goal 30 m ahead
    and to the left, under the node's lock (a :meth:`wm.serve.LiveNode.call`)."""
    from wm.bg import Planner
    from wm.whatif import WhatIf

    with live.lock:  # the server reads the KD too: not at the same time
        node = live.node
        wi = WhatIf(node.kd, node.stack, self_id=node.self_id)
        start = wi.start_from_kd()
        goal = start.xy + 30.0 * np.array([math.cos(start.yaw + 0.5), math.sin(start.yaw + 0.5)])
        return start, goal, Planner(wi, cfg).plan(goal, start=start)


def _post(base: str, path: str, body: dict) -> tuple[int, dict]:
    import urllib.error
    import urllib.request

    req = urllib.request.Request(
        base + path, data=json.dumps(body).encode(),
        headers={"Content-Type": "application/json", "Authorization": f"Bearer {TOKEN}"},
    )  # fmt: skip
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"null")


def test_what_if_start_and_traces_are_optional_and_checked(server) -> None:
    """A request without ``start`` and ``traces`` gets the answer it always had (no traces);
    with them, the rollout starts where asked and the traces hold full-precision steps; a
    start too far from the newest cycle, or with a negative speed, and a plan path with an
    infinite point get a 4xx naming the value."""
    live, base = server
    deadline = time.time() + 60
    while live.status.cycles < 1 and time.time() < deadline:
        time.sleep(0.1)
    plan = {"name": "go", "t_s": [0.0], "speed_mps": [3.0], "curvature_1pm": [0.05]}
    code, plain = _post(base, "/v1/whatif", {"plans": [plan]})
    assert code == 200, plain
    assert "t_s" not in plain and "start" not in plain and "trace" not in plain["plans"][0]
    start = {"xy": [1.25, -2.5], "yaw_rad": 0.3, "speed_mps": 2.0, "t0_ns": plain["t0_ns"]}
    code, traced = _post(base, "/v1/whatif", {"plans": [plan], "start": start, "traces": True})
    assert code == 200, traced
    assert traced["start"]["xy"] == start["xy"] and traced["t0_ns"] == start["t0_ns"]
    tr = traced["plans"][0]["trace"]
    assert tr["xy"][0] == start["xy"] and len(tr["xy"]) == len(traced["t_s"]) == len(tr["cost"])
    far = start | {"t0_ns": plain["t0_ns"] + 11 * 10**9}
    code, ans = _post(base, "/v1/whatif", {"plans": [plan], "start": far})
    assert code == 400 and f"start.t0_ns={far['t0_ns']}" in ans["detail"]
    code, ans = _post(base, "/v1/whatif", {"plans": [plan], "start": start | {"speed_mps": -1}})
    assert code == 422 and "speed_mps" in json.dumps(ans)
    code, ans = _post(base, "/v1/plan", {"xy": [[0.0, 0.0], [1e9, 0.0]]})
    assert code == 422 and "xy" in json.dumps(ans)


def test_bg_refuses_bad_arguments_and_an_unreachable_server_in_one_line(server) -> None:
    """Exit status 2 and one line naming the value: a goal that is not two numbers, a wrong
    token (the server's 401), and a server nobody listens at."""
    from serving import free_port

    _, base = server
    bad_goal = _run_bg(base, "--goal", "3,north", timeout_s=60)
    assert bad_goal.returncode == 2 and "'3,north'" in bad_goal.stderr
    assert len(bad_goal.stderr.strip().splitlines()) == 1
    env = os.environ | {"PYTHONPATH": str(REPO), "WRONG": "nope"}
    cmd = [sys.executable, "-m", "wm.bg", "--url", base, "--goal", "0,0", "--token-env", "WRONG"]
    wrong = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60)
    assert wrong.returncode == 2 and "HTTP 401" in wrong.stderr
    nobody = f"http://127.0.0.1:{free_port()}"
    gone = _run_bg(nobody, "--goal", "0,0", timeout_s=60)
    assert gone.returncode == 2 and "cannot reach the server" in gone.stderr
    assert nobody in gone.stderr and len(gone.stderr.strip().splitlines()) == 1
