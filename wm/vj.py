"""Value judgment (reference 001, 4.3): cost layers, worth of entities, confidence of KD items,
the entities-of-attention list, and the evaluation of simulated plans.

"Value judgment computes costs, risks and benefits of actions and plans, estimates the
importance and value of objects, events and situations, and assesses the reliability of
information" (4.3). Weights live in :class:`~wm.config.VJConfig`; all values are
dimensionless utilities as in the KD (docs/kd.md, units).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import kd_store
from core.errors import EngineError
from kd_store import EntityFrame, Status, Value
from maps.level import MapLevel
from wm.config import VJConfig


class VJError(EngineError, ValueError):
    """A value-judgment request that cannot be answered (names the value)."""


# --- worth and confidence ----------------------------------------------------------------------


def class_value(kd: kd_store.KnowledgeDatabase, class_name: str | None) -> Value:
    """The value of the most specific class in ``class_name``'s lineage that has one."""
    if class_name is None or class_name not in kd.classes:
        return Value()
    for name in kd.classes.lineage(class_name):
        v = kd.classes.get(name).value
        if v != Value():
            return v
    return Value()


def entity_value(kd: kd_store.KnowledgeDatabase, f: EntityFrame) -> Value:
    """An entity's own value when it has one, else its class value (4.3: worth from class)."""
    return f.value if f.value != Value() else class_value(kd, f.most_specific_class)


def confidence(f: EntityFrame) -> float:
    """Confidence (0..1) in a KD item (4.3, reliability of information): its filter
    confidence, halved for unconfirmed hypotheses and zero when denied or gone. The cost layer
    weighs an entity's class cost by it (:func:`cost_window`)."""
    scale = {Status.CONFIRMED: 1.0, Status.HYPOTHESIZED: 0.5}.get(f.status, 0.0)
    return float(f.confidence) * scale


# --- cost layers -------------------------------------------------------------------------------


def cost_window(level: MapLevel, kd: kd_store.KnowledgeDatabase, cfg: VJConfig) -> np.ndarray:
    """The traversal cost (size, size) float32 (dimensionless) of a level in window order.

    Per cell: ``w_traversability * (1 - traversability)`` plus ``w_uncertainty *
    min(1, sqrt(elevation_var) / sigma_ref_m)``; ``w_unknown`` where the elevation is unknown;
    plus, where SP labelled the cell with an entity, that entity's cost (its own value, else its
    class value) times :func:`confidence` in it, so denied or gone entities add nothing."""
    return level.to_window(_cost(level, kd, cfg))


def _cost(level: MapLevel, kd: kd_store.KnowledgeDatabase, cfg: VJConfig) -> np.ndarray:
    """:func:`cost_window` in the level's storage order (per cell, so no window is unrolled)."""
    elev = level.storage("elevation")
    unknown = ~np.isfinite(elev)
    trav = np.nan_to_num(level.storage("traversability"), nan=0.0)
    sigma = np.sqrt(np.nan_to_num(level.storage("elevation_var"), nan=cfg.sigma_ref_m**2))
    cost = cfg.w_traversability * (1.0 - trav) + cfg.w_uncertainty * np.minimum(
        1.0, sigma / cfg.sigma_ref_m
    )
    cost[unknown] = cfg.w_unknown
    ids = level.storage("entity_id")
    labelled = ids >= 0
    if labelled.any():
        u, inv = np.unique(ids[labelled], return_inverse=True)
        per = np.array([_entity_cost(kd, int(i)) for i in u])
        cost[labelled] += per[inv]
    return cost.astype(np.float32)


def _entity_cost(kd: kd_store.KnowledgeDatabase, entity_id: int) -> float:
    """An entity's expected cost in a cell it labels: its cost times the confidence in it."""
    try:
        f = kd.get(entity_id)
    except kd_store.KDError:  # forgotten since SP wrote it
        return 0.0
    return entity_value(kd, f).cost * confidence(f)


def write_cost_layer(level: MapLevel, kd: kd_store.KnowledgeDatabase, cfg: VJConfig) -> None:
    """Write :func:`cost_window` into the level's ``cost`` layer."""
    level.storage("cost")[...] = _cost(level, kd, cfg)


# --- attention ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Attention:
    """Entities of attention, highest priority first: ``ids`` (K,) int64, ``priority`` (K,)."""

    ids: np.ndarray
    priority: np.ndarray


def attention(
    kd: kd_store.KnowledgeDatabase,
    position_xy: np.ndarray,
    cfg: VJConfig,
    plan_xy: np.ndarray | None = None,
    skip: int = -1,
    t_now_ns: int | None = None,
) -> Attention:
    """Rank world-frame entities by proximity, danger (class risk), novelty (not yet
    confirmed) and relevance to the plan (within ``relevance_radius_m`` of ``plan_xy`` (S, 2));
    keep the top ``attention_size`` (4.3; 4.4.11: the entities-of-attention list).
    ``position_xy`` and ``plan_xy`` are world metres; ``plan_xy`` None or empty: no plan."""
    if plan_xy is not None:
        plan_xy = np.asarray(plan_xy, dtype=np.float64)
        shaped = plan_xy.ndim == 2 and plan_xy.shape[1] >= 2
        if not shaped or not np.all(np.isfinite(plan_xy[:, :2])):
            bad = "non-finite values" if shaped else f"shape {plan_xy.shape}"
            raise VJError(f"attention: plan_xy must be a finite (S, 2) array of world m, got {bad}")
    frames = [
        f
        for f in kd.entities()
        if f.id != skip and f.state is not None and f.state.frame == "world"
        and f.status not in (Status.DENIED, Status.GONE)
    ]  # fmt: skip
    if not frames:
        return Attention(np.zeros(0, np.int64), np.zeros(0))
    xy = np.array([f.state.position_xyz[:2] for f in frames])  # type: ignore[union-attr]
    d = np.linalg.norm(xy - np.asarray(position_xy, dtype=np.float64)[:2], axis=1)
    risk = np.array([entity_value(kd, f).risk for f in frames])
    novel = np.array([f.status != Status.CONFIRMED for f in frames], dtype=np.float64)
    near_plan = np.zeros(len(frames))
    if plan_xy is not None and len(plan_xy):
        dp = np.linalg.norm(xy[:, None, :] - plan_xy[None, :, :2], axis=2).min(1)
        near_plan = (dp <= cfg.relevance_radius_m).astype(np.float64)
    pr = (
        cfg.w_proximity / (1.0 + d / cfg.proximity_scale_m)
        + cfg.w_danger * risk
        + cfg.w_novelty * novel
        + cfg.w_relevance * near_plan
    )
    order = np.argsort(-pr, kind="stable")[: cfg.attention_size]
    return Attention(np.array([frames[i].id for i in order], np.int64), pr[order])


# --- plan evaluation ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Evaluation:
    """Per plan (P,): ``cost``, ``risk``, ``benefit`` and ``score = benefit - cost - risk``."""

    cost: np.ndarray
    risk: np.ndarray
    benefit: np.ndarray

    @property
    def score(self) -> np.ndarray:
        return self.benefit - self.cost - self.risk

    @property
    def best(self) -> int:
        return int(np.argmax(self.score))


def evaluate(result, goal_xy: np.ndarray | None, cfg: VJConfig) -> Evaluation:
    """Cost, risk and benefit of simulated plans (a :class:`wm.whatif.WhatIfResult`); see
    :class:`~wm.config.VJConfig` for the formulas (4.3: "the evaluation of a plan")."""
    dt = result.dt_s
    step_cost = np.nan_to_num(result.cost, nan=cfg.w_unknown) + cfg.w_time
    cost = step_cost.sum(axis=1) * dt
    near = result.entity_risk * np.exp(-np.maximum(result.clearance_m, 0.0) / cfg.clearance_scale_m)
    risk = near.max(axis=1) if near.shape[1] else np.zeros(len(cost))
    risk = np.where(result.collision_entity >= 0, cfg.collision_risk, risk)
    blocked = np.fmin.reduce(result.traversability, axis=1) <= 0.0  # NaN (unknown) ignored
    risk = risk + cfg.collision_risk * blocked
    if goal_xy is None:
        benefit = cfg.w_progress * result.distance_m
    else:
        g = np.asarray(goal_xy, dtype=np.float64)[:2]
        d0 = np.linalg.norm(result.xy[:, 0] - g, axis=1)
        d1 = np.linalg.norm(result.xy[:, -1] - g, axis=1)
        benefit = cfg.w_progress * (d0 - d1)
    return Evaluation(cost, risk, benefit)
