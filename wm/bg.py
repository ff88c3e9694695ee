"""A behavior-generation consumer (reference 001, 4.1): the planning loop at one level.

"While the planning period is open" the planner hypothesizes tentative plans batch by batch,
asks What If to simulate each batch, asks value judgment to evaluate it, and keeps the best so
far ("the tentative_plan replaces the current plan in the current_best_plan_buffer", 4.1).
The tentative plans are, in this order: the plan selected last period continued (its path
shifted by the time elapsed and extended to the horizon, 4.1.7), then a fan of constant speed
and curvature controls, slowest first. The planning period is ``PlannerConfig.budget_s`` of
wall time: once it is over no further batch is hypothesized (the first always is). Replans
every ``replan_period_s``. It uses only the What If and VJ interfaces, and optionally tells the
node its plan through a callback (``WorldModelNode.set_plan``), never the KD's internals.

What If is anything with :class:`WhatIfService`'s two methods: :class:`wm.whatif.WhatIf` in the
node's process, or :class:`wm.remote.RemoteWhatIf` over a live node's HTTP API, which is how
``wm bg`` (equally ``python -m wm.bg``) plans in a process of its own:

    wm bg --url http://127.0.0.1:8765 --goal 60,20 [--cycles 10] [--json]
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from wm import vj
from wm.config import PlannerConfig, VJConfig
from wm.whatif import ControlPlan, Plan, Start, WaypointPlan, WhatIfResult


class WhatIfService(Protocol):
    """What the planner asks of What If (:class:`wm.whatif.WhatIf` has both)."""

    def start_from_kd(self) -> Start:
        """The vehicle's present state (world frame)."""
        ...

    def simulate(self, plans: list[Plan], *, level: str, start: Start | None) -> WhatIfResult:
        """Every plan rolled out at ``level`` from ``start``."""
        ...


@dataclass(frozen=True)
class Selected:
    """The plan kept: its index among the candidates, the plan, its rollout trace (t_s (S+1,)
    seconds after the start, xy (S+1, 2) world m, yaw (S+1,) rad), its evaluation (cost, risk,
    benefit, dimensionless), its first collision (-1: none), how many candidates were weighed,
    whether the planning budget ran out before every candidate was, and the wall time (s)."""

    index: int
    plan: Plan
    t_s: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    cost: float
    risk: float
    benefit: float
    collision_entity: int
    n_candidates: int
    budget_hit: bool
    elapsed_s: float


@dataclass
class _Best:
    """The best candidate of the batches so far by ``key`` (VJ score, or distance)."""

    key: float
    index: int
    res: WhatIfResult
    row: int
    ev: vj.Evaluation


class Planner:
    """Hypothesize -> What If -> VJ -> select (module docstring).

    ``on_select``, if given, is called with each selected plan's path (S+1, 2) world metres,
    e.g. ``WorldModelNode.set_plan`` so the node's attention weighs relevance to the plan."""

    def __init__(
        self,
        whatif: WhatIfService,
        config: PlannerConfig | None = None,
        vj_config: VJConfig | None = None,
        on_select: Callable[[np.ndarray], None] | None = None,
    ) -> None:
        self.whatif = whatif
        self.config = config or PlannerConfig()
        self.vj_config = vj_config or VJConfig()
        self.on_select = on_select
        self.last: Selected | None = None
        self.last_t_ns: int | None = None

    def candidates(self, t0_ns: int | None = None) -> list[Plan]:
        """The tentative plans in the order they are hypothesized: the last selected plan
        continued to a start at ``t0_ns`` (:meth:`continued`; left out when ``t0_ns`` is None
        or there is nothing to continue), then every (speed, curvature) pair held over the
        horizon, slowest first."""
        out: list[Plan] = []
        cont = None if t0_ns is None else self.continued(t0_ns)
        if cont is not None:
            out.append(cont)
        t = np.array([0.0])
        out += [
            ControlPlan(t, np.array([v]), np.array([k]), f"v{v:g}_k{k:g}")
            for v in sorted(self.config.speeds_mps)
            for k in self.config.curvatures_1pm
        ]
        return out

    def continued(self, t0_ns: int) -> WaypointPlan | None:
        """The last selected plan re-timed to start at ``t0_ns``: the waypoints of its path
        after the time elapsed since it started, each earlier by that time, and one more at the
        horizon, along its last step's velocity (4.1.7: "all the planned waypoints are shifted
        left ... and a new way point is generated" at the horizon). None without a last plan,
        for a ``t0_ns`` before it, or when fewer than two of its waypoints are still ahead."""
        last, t_last = self.last, self.last_t_ns
        if last is None or t_last is None or t0_ns < t_last:
            return None
        elapsed = (t0_ns - t_last) * 1e-9
        t = last.t_s - elapsed
        ahead = t > 1e-9  # the waypoint at the elapsed time is where the start is
        if np.count_nonzero(ahead) < 2:
            return None
        t_new, xy_new = t[ahead], last.xy[ahead]
        horizon = float(last.t_s[-1])
        if horizon - t_new[-1] > 1e-9:
            v = (last.xy[-1] - last.xy[-2]) / (last.t_s[-1] - last.t_s[-2])
            xy_new = np.vstack([xy_new, xy_new[-1] + v * (horizon - t_new[-1])])
            t_new = np.append(t_new, horizon)
        return WaypointPlan(t_new, xy_new, "continued")

    def due(self, t_ns: int) -> bool:
        """Whether a replanning period has passed since the last plan."""
        return self.last_t_ns is None or t_ns - self.last_t_ns >= self.config.replan_period_s * 1e9

    def plan(self, goal_xy: np.ndarray, start: Start | None = None) -> Selected:
        """One planning cycle towards ``goal_xy`` (world m) from ``start`` (default: the KD's
        self state through What If). Plans that collide or whose clearance is under
        ``min_clearance_m`` are kept only when nothing else is left (then the one going least
        far is chosen). Batches of ``batch_size`` are weighed until the candidates or the
        ``budget_s`` run out; ``Selected.budget_hit`` says which."""
        t_begin = time.perf_counter()
        cfg = self.config
        start = start or self.whatif.start_from_kd()
        plans = self.candidates(start.t0_ns)
        best: _Best | None = None  # the best safe plan so far
        least: _Best | None = None  # the plan going least far, if nothing is safe
        n, budget_hit = 0, False
        for b0 in range(0, len(plans), cfg.batch_size):
            if n and time.perf_counter() - t_begin >= cfg.budget_s:
                budget_hit = True
                break
            batch = plans[b0 : b0 + cfg.batch_size]
            res = self.whatif.simulate(batch, level=cfg.level, start=start)
            ev = vj.evaluate(res, goal_xy, self.vj_config)
            n += len(batch)
            unsafe = (res.collision_entity >= 0) | (res.min_clearance_m < cfg.min_clearance_m)
            score = np.where(unsafe, -np.inf, ev.score)
            j = int(np.argmax(score))
            if not unsafe[j] and (best is None or score[j] > best.key):
                best = _Best(float(score[j]), b0 + j, res, j, ev)
            k = int(np.argmin(res.distance_m))
            if least is None or -res.distance_m[k] > least.key:
                least = _Best(-float(res.distance_m[k]), b0 + k, res, k, ev)
        pick = best or least
        assert pick is not None  # the first batch always runs
        res, j, ev = pick.res, pick.row, pick.ev
        sel = Selected(
            pick.index, plans[pick.index], res.t_s, res.xy[j], res.yaw[j], float(ev.cost[j]),
            float(ev.risk[j]), float(ev.benefit[j]), int(res.collision_entity[j]), n,
            budget_hit, time.perf_counter() - t_begin,
        )  # fmt: skip
        self.last, self.last_t_ns = sel, res.t0_ns
        if self.on_select is not None:
            self.on_select(sel.xy.copy())
        return sel


if __name__ == "__main__":  # python -m wm.bg ...: the same as ``wm bg ...``
    import sys

    from wm.cli import main

    sys.exit(main(["bg", *sys.argv[1:]]))
