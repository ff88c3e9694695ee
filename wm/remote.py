"""Behavior generation in a process of its own, against a live node's HTTP API (:mod:`wm.serve`).

:class:`RemoteWhatIf` gives :class:`wm.bg.Planner` what it uses of :class:`wm.whatif.WhatIf`
(``start_from_kd`` and ``simulate``) through the API alone: the start is the node's self state
(``GET /v1/whatif/start``), and every batch of plans is rolled out by the node's What If from
that one start (``POST /v1/whatif`` with ``start`` and ``traces``), so a planning cycle's
batches share it while the node runs on; each batch is checked against the KD as of the newest
cycle when it arrives. The answer's per-step arrays make a real
:class:`~wm.whatif.WhatIfResult`, which the planner judges with its own value judgment
(:func:`wm.vj.evaluate`), exactly as in the node's process.

:func:`run_bg` is the loop of ``wm bg`` (and ``python -m wm.bg``): wait for a new cycle
(``/v1/status``), plan towards a goal when a replanning period has passed, print one line per
plan, and tell the node the plan chosen (``POST /v1/plan``).

Frames and units: world frame (the node's), metres, radians, seconds after ``t0_ns``; times
int64 ns of log time.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from typing import TextIO

import numpy as np

from core.errors import EngineError
from wm.bg import Planner, Selected
from wm.client import Client
from wm.config import PlannerConfig
from wm.whatif import (
    STEP_FLOATS,
    ControlPlan,
    Plan,
    Start,
    WaypointPlan,
    WhatIfResult,
    check_plan,
)

#: wall seconds between two looks at ``/v1/status`` while waiting for a new cycle
POLL_S = 0.05


class RemoteError(EngineError, RuntimeError):
    """An answer of the node that the planner cannot use (names the field or the value)."""


def plan_dict(plan: Plan) -> dict:
    """``plan`` as ``POST /v1/whatif`` takes it: ``{"name", "t_s", "xy"}`` (waypoints, world m)
    or ``{"name", "t_s", "speed_mps", "curvature_1pm"}`` (controls); floats exact (JSON keeps
    every digit of a float64)."""
    t = np.asarray(plan.t_s, dtype=np.float64).tolist()
    if isinstance(plan, WaypointPlan):
        return {"name": plan.name, "t_s": t, "xy": np.asarray(plan.xy, np.float64).tolist()}
    return {
        "name": plan.name, "t_s": t,
        "speed_mps": np.asarray(plan.speed_mps, np.float64).tolist(),
        "curvature_1pm": np.asarray(plan.curvature_1pm, np.float64).tolist(),
    }  # fmt: skip


def start_dict(start: Start) -> dict:
    """``start`` as ``POST /v1/whatif`` takes it (world frame, m, rad, m/s, ns)."""
    return {"xy": np.asarray(start.xy, np.float64)[:2].tolist(), "yaw_rad": float(start.yaw),
            "speed_mps": float(start.speed_mps), "t0_ns": int(start.t0_ns)}  # fmt: skip


def start_of(answer: dict) -> Start:
    """The :class:`Start` of a ``/v1/whatif/start`` answer (or a traces answer's ``start``)."""
    try:
        xy = np.array(answer["xy"], dtype=np.float64)
        return Start(xy, float(answer["yaw_rad"]), float(answer["speed_mps"]),
                     int(answer["t0_ns"]))  # fmt: skip
    except (KeyError, TypeError, ValueError) as e:
        raise RemoteError(f"a start state without a usable {e}: {answer!r:.200}") from None


def _floats(values: list, null: float) -> np.ndarray:
    """A JSON list of numbers as float64, null as ``null`` (NaN or inf: the server's words)."""
    return np.array([null if v is None else v for v in values], dtype=np.float64)


def result_of(answer: dict) -> WhatIfResult:
    """The :class:`WhatIfResult` of a ``POST /v1/whatif`` answer made with ``traces``: nulls
    are NaN (unknown) in map samples and ``collision_t_s``, +inf in ``clearance_m`` and
    ``min_clearance_m`` (no entity near), -1 in ``collision_entity`` (no collision)."""
    if "t_s" not in answer or any("trace" not in p for p in answer.get("plans", [])):
        raise RemoteError(
            "the server's /v1/whatif answer has no traces: it predates the 'traces' field"
        )
    plans = answer["plans"]
    per_step: dict[str, list[np.ndarray]] = {}
    for p in plans:
        tr = p["trace"]
        for k, null in STEP_FLOATS.items():
            per_step.setdefault(k, []).append(_floats(tr[k], null))
        per_step.setdefault("xy", []).append(np.array(tr["xy"], dtype=np.float64))
        per_step.setdefault("nearest_entity", []).append(np.array(tr["nearest_entity"], np.int64))
    arrays = {k: np.stack(v) for k, v in per_step.items()}
    return WhatIfResult(
        level=str(answer["level"]), t0_ns=int(answer["t0_ns"]), dt_s=float(answer["dt_s"]),
        t_s=np.array(answer["t_s"], dtype=np.float64), **arrays,
        distance_m=np.array([p["distance_m"] for p in plans], dtype=np.float64),
        min_clearance_m=_floats([p["min_clearance_m"] for p in plans], math.inf),
        collision_entity=np.array([-1 if p["collision_entity"] is None else p["collision_entity"]
                                   for p in plans], dtype=np.int64),
        collision_t_s=_floats([p["collision_t_s"] for p in plans], math.nan),
        limited_steps=np.array([p["limited_steps"] for p in plans], dtype=np.int64),
        names=[str(p["name"]) for p in plans],
    )  # fmt: skip


class RemoteWhatIf:
    """What If of the live node at ``client``'s server, for :class:`wm.bg.Planner` (module
    docstring). ``start_cycle_t_ns`` is the cycle the newest start came from and
    ``answer_cycles_t_ns`` the cycles of the What If answers since it (int64 ns, log time)."""

    def __init__(self, client: Client) -> None:
        self.client = client
        self.start_cycle_t_ns: int | None = None
        self.answer_cycles_t_ns: list[int] = []

    def start_from_kd(self) -> Start:
        """The node's self state now, as its What If would start from it (world frame)."""
        answer = self.client.whatif_start()
        self.start_cycle_t_ns = int(answer["cycle_t_ns"])
        self.answer_cycles_t_ns = []
        return start_of(answer)

    def simulate(
        self,
        plans: list[Plan],
        *,
        level: str = "subsystem",
        start: Start | None = None,
        horizon_s: float | None = None,
    ) -> WhatIfResult:
        """Every plan rolled out by the node at ``level`` from ``start`` (default: the node's
        self state now, :meth:`start_from_kd`) over ``horizon_s`` (default: the level's),
        against the node's maps and entities. Plans are checked here first (the same
        :class:`~wm.whatif.WhatIfError` as in-process); the server's refusals raise
        :class:`~wm.client.ClientError` with its words."""
        if not plans:
            raise RemoteError("simulate needs at least one plan")
        for i, p in enumerate(plans):
            if not isinstance(p, WaypointPlan | ControlPlan):
                raise RemoteError(f"plan {i}: not a WaypointPlan or ControlPlan: {type(p)}")
            check_plan(p, i)
        start = start or self.start_from_kd()
        sent = start_dict(start)
        answer = self.client.simulate([plan_dict(p) for p in plans], level, horizon_s,
                                      start=sent, traces=True)  # fmt: skip
        got = start_of(answer.get("start") or {})
        if got.t0_ns != start.t0_ns or not np.array_equal(got.xy, sent["xy"]):
            # a server that ignored ``start`` rolled out from another state than the one asked
            raise RemoteError(
                f"the server rolled out from t0_ns={got.t0_ns}, xy={got.xy.tolist()}, not the "
                f"start sent (t0_ns={start.t0_ns}, xy={sent['xy']})"
            )
        self.answer_cycles_t_ns.append(int(answer["cycle_t_ns"]))
        return result_of(answer)

    def tell_plan(self, xy: np.ndarray) -> None:
        """Tell the node the plan chosen: its path (S+1, 2) world m (``POST /v1/plan``); an
        ``on_select`` for :class:`wm.bg.Planner`."""
        self.client.set_plan(np.asarray(xy, dtype=np.float64)[:, :2].tolist())


# --- the planning process --------------------------------------------------------------------


def plan_record(sel: Selected, start: Start, remote: RemoteWhatIf) -> dict:
    """One plan as ``wm bg --json`` prints it: times ns, path ``xy`` (S+1, 2) world m at ``t_s``
    (S+1,) s after ``t0_ns``, the start (world m, rad, m/s), cost / risk / benefit, the first
    collision (None: none), the wall time, and the cycles its answers came from."""
    return {
        "t0_ns": int(start.t0_ns), "cycle_t_ns": remote.start_cycle_t_ns,
        "answer_cycles_t_ns": list(remote.answer_cycles_t_ns),
        "plan": sel.plan.name, "index": sel.index, "cost": sel.cost, "risk": sel.risk,
        "benefit": sel.benefit,
        "collision_entity": None if sel.collision_entity < 0 else sel.collision_entity,
        "elapsed_ms": 1e3 * sel.elapsed_s, "candidates": sel.n_candidates,
        "budget_hit": sel.budget_hit, "start": start_dict(start),
        "t_s": sel.t_s.tolist(), "xy": sel.xy.tolist(),
    }  # fmt: skip


def plan_line(rec: dict) -> str:
    """One plan as a line of text (``plan_record``'s main fields)."""
    hit = rec["collision_entity"]
    return (
        f"t0_ns={rec['t0_ns']} cycle_t_ns={rec['cycle_t_ns']} plan={rec['plan']} "
        f"index={rec['index']} cost={rec['cost']:.3f} risk={rec['risk']:.3f} "
        f"collision={'none' if hit is None else f'entity {hit}'} "
        f"elapsed_ms={rec['elapsed_ms']:.1f} candidates={rec['candidates']}"
        + (" budget_hit" if rec["budget_hit"] else "")
    )


def run_bg(
    client: Client,
    goal_xy: np.ndarray,
    config: PlannerConfig,
    cycles: int | None = None,
    as_json: bool = False,
    tell: bool = True,
    out: TextIO | None = None,
    sleep: Callable[[float], None] = time.sleep,
) -> int:
    """Plan towards ``goal_xy`` (world m) against the node at ``client``: at each new cycle
    (``/v1/status``) once ``config.replan_period_s`` of log time has passed since the last
    plan's start, one :meth:`Planner.plan` over :class:`RemoteWhatIf`; one line per plan on
    ``out`` (JSON with ``as_json``); the plan told to the node when ``tell``. Stops after
    ``cycles`` plans, or when the node's log has ended and its last cycle is planned over.
    Returns the number of plans made."""
    import sys

    out = out or sys.stdout
    remote = RemoteWhatIf(client)
    planner = Planner(remote, config, on_select=remote.tell_plan if tell else None)
    last_cycle, made = -1, 0
    while cycles is None or made < cycles:
        st = client.status()
        cycle = int(st["cycle_t_ns"])
        fresh = cycle > last_cycle and cycle >= 0
        if not (fresh and planner.due(cycle)):
            if st["done"]:  # no cycle will come: the log (or the node) has ended
                break
            sleep(POLL_S)
            continue
        start = remote.start_from_kd()
        sel = planner.plan(goal_xy, start=start)
        rec = plan_record(sel, start, remote)
        print(json.dumps(rec) if as_json else plan_line(rec), file=out, flush=True)
        last_cycle = max(cycle, remote.start_cycle_t_ns or -1)
        made += 1
    return made


def parse_goal(text: str) -> np.ndarray:
    """``"x,y"`` (world m) as an array (2,); RemoteError naming the text otherwise."""
    try:
        xy = np.array([float(v) for v in text.split(",")], dtype=np.float64)
    except ValueError:
        xy = np.zeros(0)
    if xy.shape != (2,) or not np.all(np.isfinite(xy)):
        raise RemoteError(f"--goal {text!r}: need 'x,y', two finite numbers in world metres")
    return xy


def check_url(url: str) -> str:
    """``url`` if it is an http(s) address with a host (``http://127.0.0.1:8765``)."""
    import urllib.parse

    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise RemoteError(f"--url {url!r}: need an http(s) address such as http://127.0.0.1:8765")
    return url
