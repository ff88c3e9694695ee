"""A behavior-generation consumer (reference 001, 4.1): the planning loop at one level.

Within a planning period the planner hypothesizes tentative plans (a fan of constant speed
and curvature controls, plus the last selected plan re-timed), asks What If to simulate them,
asks value judgment to evaluate them, and keeps the best ("the plan selector keeps the best",
4.1). Replans every ``replan_period_s``. It uses only the What Is / What If / VJ interfaces,
never the KD's internals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wm import vj
from wm.config import PlannerConfig, VJConfig
from wm.whatif import ControlPlan, Start, WhatIf, WhatIfResult


@dataclass(frozen=True)
class Selected:
    """The plan kept: its index among the candidates, the plan, its rollout trace (xy (S+1, 2),
    t_s (S+1,)), its evaluation, and how many candidates were weighed."""

    index: int
    plan: ControlPlan
    t_s: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    cost: float
    risk: float
    benefit: float
    collision_entity: int
    n_candidates: int


class Planner:
    """Hypothesize -> What If -> VJ -> select (module docstring)."""

    def __init__(
        self, whatif: WhatIf, config: PlannerConfig | None = None, vj_config: VJConfig | None = None
    ) -> None:
        self.whatif = whatif
        self.config = config or PlannerConfig()
        self.vj_config = vj_config or VJConfig()
        self.last: Selected | None = None
        self.last_t_ns: int | None = None

    def candidates(self) -> list[ControlPlan]:
        """The tentative plans: every (speed, curvature) pair held over the horizon."""
        t = np.array([0.0])
        return [
            ControlPlan(t, np.array([v]), np.array([k]), f"v{v:g}_k{k:g}")
            for v in self.config.speeds_mps
            for k in self.config.curvatures_1pm
        ]

    def due(self, t_ns: int) -> bool:
        """Whether a replanning period has passed since the last plan."""
        return self.last_t_ns is None or t_ns - self.last_t_ns >= self.config.replan_period_s * 1e9

    def plan(self, goal_xy: np.ndarray, start: Start | None = None) -> Selected:
        """One planning cycle towards ``goal_xy`` (world m) from ``start`` (default: the KD's
        self state). Plans that collide or whose clearance is under ``min_clearance_m`` are
        kept only when nothing else is left (then the slowest is chosen)."""
        plans = self.candidates()
        res: WhatIfResult = self.whatif.simulate(plans, level=self.config.level, start=start)
        ev = vj.evaluate(res, goal_xy, self.vj_config)
        score = ev.score.copy()
        unsafe = (res.collision_entity >= 0) | (res.min_clearance_m < self.config.min_clearance_m)
        score[unsafe] -= 1e6
        i = int(np.argmax(score))
        if unsafe[i]:  # nothing safe: stop as hard as the vehicle can
            i = int(np.argmin(res.distance_m))
        sel = Selected(
            i, plans[i], res.t_s, res.xy[i], res.yaw[i], float(ev.cost[i]), float(ev.risk[i]),
            float(ev.benefit[i]), int(res.collision_entity[i]), len(plans),
        )  # fmt: skip
        self.last, self.last_t_ns = sel, res.t0_ns
        return sel
