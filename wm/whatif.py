"""What If (reference 001, 4.2 item 4): simulate candidate plans and say what would happen.

"The WM simulates the probable results of hypothesized plans" (4.2); the planner then asks
value judgment to evaluate them (4.1, the planning loop). A plan is timed waypoints or timed
controls, at one map level (its step, :class:`~wm.config.WhatIfConfig`, and its horizon, the
KD's memory horizon of the level, ``kd.memory.horizons_s`` of the engine configuration). Each
plan is rolled out with a kinematic model of the vehicle (``node.vehicle``) with limits
(speed, acceleration, curvature, yaw rate); along the swept footprint the level's layers are
sampled (elevation, slope, traversability, cost, unknown cells); entity boxes from the KD,
moving ones at their constant-velocity predictions for each step, are checked for collision
with the vehicle's box by python-fcl (footprint collision: both boxes stand on one plane,
2.5D). All plans of a call are rolled out together (numpy over plans); fcl runs only where
footprint circles meet.

What If reads the KD (the self state, the object entities near the start, their values) and
the map stack (four layers of the level asked: :data:`SAMPLED_LAYERS`) and writes neither.
:class:`WhatIfCopy` holds exactly that, taken from a KD and a stack between two node cycles;
:meth:`WhatIf.over` answers from such a copy as :class:`WhatIf` over the KD and the stack
would at that moment, so a server answers without holding the node up (:mod:`wm.serve`).

Frames and units: world frame, metres, radians, seconds after ``t0_ns``; yaw about z.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

import kd_store
from core.errors import EngineError
from kd_store import Level, State, Status
from maps.level import MapLevel
from maps.stack import MapStack
from wm.config import NodeConfig, VehicleConfig, WhatIfConfig
from wm.shapes import EntityBoxes, boxes_of
from wm.vj import entity_value

if TYPE_CHECKING:  # at run time imported when needed: it imports SP, the odometry and the maps
    from wm.engine_config import EngineConfig


class WhatIfError(EngineError, ValueError):
    """A plan or request What If refuses (names the plan index and the offending value)."""


@dataclass(frozen=True)
class WaypointPlan:
    """Timed waypoints: ``t_s`` (K,) seconds after the start, strictly increasing, >= 0;
    ``xy`` (K, 2) world metres. Between waypoints the path is linear in time."""

    t_s: np.ndarray
    xy: np.ndarray
    name: str = ""


@dataclass(frozen=True)
class ControlPlan:
    """Timed controls, each held from ``t_s[k]`` to the next: ``speed_mps`` (K,) wanted speed,
    ``curvature_1pm`` (K,) wanted path curvature (1/m, left positive)."""

    t_s: np.ndarray
    speed_mps: np.ndarray
    curvature_1pm: np.ndarray
    name: str = ""


Plan = WaypointPlan | ControlPlan


@dataclass(frozen=True)
class Start:
    """The vehicle state a rollout starts from (world frame): position (2,) m, yaw rad,
    speed m/s, at ``t0_ns``."""

    xy: np.ndarray
    yaw: float
    speed_mps: float
    t0_ns: int


#: A plan's per-step float arrays (S+1,) by name, each with what a non-finite value means
#: there: NaN an unknown map sample (or no motion state), +inf no entity near.
STEP_FLOATS: dict[str, float] = {
    "yaw": np.nan, "speed": np.nan, "elevation": np.nan, "slope": np.nan,
    "traversability": np.nan, "cost": np.nan, "unknown_fraction": np.nan,
    "clearance_m": np.inf, "entity_risk": np.nan,
}  # fmt: skip

#: The map layers a rollout samples along its footprint (:meth:`WhatIf._sample_maps`); all a
#: :class:`LevelCopy` holds.
SAMPLED_LAYERS: tuple[str, ...] = ("elevation", "slope", "traversability", "cost")

#: The KD entities a rollout is checked against: object-level ones that are neither denied
#: nor gone (:meth:`WhatIf.entities_near`).
COLLIDING_STATUSES: tuple[Status, ...] = (Status.CONFIRMED, Status.HYPOTHESIZED)


@dataclass
class WhatIfResult:
    """Per-step traces of P plans over S + 1 steps (step 0 is the start), and totals.

    t_s (S+1,) seconds after ``t0_ns``; xy (P, S+1, 2) m; yaw, speed (P, S+1).
    Sampled over the footprint at each step: elevation (mean, m), slope (max, rad),
    traversability (min, 0..1, NaN unknown), cost (max, NaN unknown), unknown_fraction (0..1).
    clearance_m (P, S+1): lower bound of the distance to the nearest entity (footprint
    circles), inf without entities; nearest_entity (P, S+1) its id (-1); entity_risk its risk.
    Totals (P,): distance_m, min_clearance_m (refined with fcl when small), collision_entity
    (-1: none) and collision_t_s (NaN: none) of the first collision, limited_steps (steps where
    a limit of the vehicle model clipped the wanted motion).
    """

    level: str
    t0_ns: int
    dt_s: float
    t_s: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    elevation: np.ndarray
    slope: np.ndarray
    traversability: np.ndarray
    cost: np.ndarray
    unknown_fraction: np.ndarray
    clearance_m: np.ndarray
    nearest_entity: np.ndarray
    entity_risk: np.ndarray
    distance_m: np.ndarray
    min_clearance_m: np.ndarray
    collision_entity: np.ndarray
    collision_t_s: np.ndarray
    limited_steps: np.ndarray
    names: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def trace(self, i: int) -> dict[str, np.ndarray]:
        """Plan ``i``'s per-step arrays by name (each (S+1,) or (S+1, 2))."""
        keys = ("xy", *STEP_FLOATS, "nearest_entity")
        return {"t_s": self.t_s, **{k: getattr(self, k)[i] for k in keys}}


# --- validation --------------------------------------------------------------------------------


def check_plan(plan: Plan, index: int) -> None:
    """Refuse non-increasing or negative times, NaN/inf values and mismatched shapes."""
    where = f"plan {index}" + (f" ({plan.name!r})" if plan.name else "")
    t = np.asarray(plan.t_s, dtype=np.float64)
    if t.ndim != 1 or len(t) < 1:
        raise WhatIfError(f"{where}: t_s must be a 1-D array of at least one time, got {t.shape}")
    if not np.all(np.isfinite(t)) or t[0] < 0:
        raise WhatIfError(f"{where}: t_s must be finite and >= 0, got {t.tolist()[:8]}")
    if np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise WhatIfError(
            f"{where}: times must increase, but t_s[{k}]={t[k]} and t_s[{k + 1}]={t[k + 1]}"
        )
    arrays = (
        {"xy": (plan.xy, (len(t), 2))}
        if isinstance(plan, WaypointPlan)
        else {
            "speed_mps": (plan.speed_mps, (len(t),)),
            "curvature_1pm": (plan.curvature_1pm, (len(t),)),
        }
    )
    for name, (a, shape) in arrays.items():
        a = np.asarray(a, dtype=np.float64)
        if a.shape != shape:
            raise WhatIfError(f"{where}: {name} must have shape {shape}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            bad = np.argwhere(~np.isfinite(a))[0].tolist()
            raise WhatIfError(f"{where}: {name} has a NaN or inf at index {bad}")


# --- the vehicle model -------------------------------------------------------------------------


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _clip(a: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``np.clip(a, lo, hi)`` for ``lo <= hi``, value for value (NaN and the sign of zero
    included): the rollout clips a few plans' values four times a step, where ``np.clip``'s
    Python-level dispatch costs several times the two ufuncs."""
    return np.minimum(hi, np.maximum(lo, a))


def rollout(
    start: Start,
    n_steps: int,
    dt: float,
    veh: VehicleConfig,
    speed_want: np.ndarray | None = None,
    curv_want: np.ndarray | None = None,
    target_xy: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Kinematic unicycle with limits, P plans at once, for ``n_steps`` steps of ``dt``.

    Either wanted controls ``speed_want``, ``curv_want`` (P, n_steps), or wanted positions
    ``target_xy`` (P, n_steps, 2) at the end of each step, tracked by pure pursuit (curvature
    ``2 sin(e) / d`` to the target at distance d and bearing error e, speed ``d / dt``).
    Returns xy (P, S+1, 2), yaw (P, S+1), speed (P, S+1), limited steps (P,)."""
    P = (target_xy if target_xy is not None else speed_want).shape[0]  # type: ignore[union-attr]
    xy = np.empty((P, n_steps + 1, 2))
    yaw = np.empty((P, n_steps + 1))
    v = np.empty((P, n_steps + 1))
    xy[:, 0], yaw[:, 0], v[:, 0] = start.xy, start.yaw, start.speed_mps
    limited = np.zeros(P, dtype=np.int64)
    for k in range(n_steps):
        p, th, vk = xy[:, k], yaw[:, k], v[:, k]
        if target_xy is not None:
            d = target_xy[:, k] - p
            dist = np.hypot(d[:, 0], d[:, 1])
            err = _wrap(np.arctan2(d[:, 1], d[:, 0]) - th)
            behind = np.abs(err) > np.pi / 2
            vw = np.where(behind, 0.0, dist / dt)  # a target behind: stop rather than reverse
            kw = np.where(dist > 1e-6, 2.0 * np.sin(err) / np.maximum(dist, 1e-6), 0.0)
        else:
            vw, kw = speed_want[:, k], curv_want[:, k]  # type: ignore[index]
        dv = _clip(vw - vk, -veh.max_decel_mps2 * dt, veh.max_accel_mps2 * dt)
        vn = _clip(vk + dv, 0.0, veh.max_speed_mps)
        kc = _clip(kw, -veh.max_curvature_1pm, veh.max_curvature_1pm)
        vm = 0.5 * (vk + vn)
        w = _clip(vm * kc, -veh.max_yaw_rate_rps, veh.max_yaw_rate_rps)
        clipped = (np.abs(vn - vw) > 1e-6) | (np.abs(kc - kw) > 1e-9)
        limited += clipped | (np.abs(w - vm * kc) > 1e-9)
        th_mid = th + 0.5 * w * dt
        xy[:, k + 1, 0] = p[:, 0] + vm * np.cos(th_mid) * dt
        xy[:, k + 1, 1] = p[:, 1] + vm * np.sin(th_mid) * dt
        yaw[:, k + 1] = _wrap(th + w * dt)
        v[:, k + 1] = vn
    return xy, yaw, v, limited


def _wanted(plans: list[Plan], times: np.ndarray) -> tuple[np.ndarray, ...]:
    """Resample plans at step ends ``times`` (S,): controls held, waypoints interpolated
    (held at the last one after it)."""
    out = []
    for plan in plans:
        t = np.asarray(plan.t_s, dtype=np.float64)
        if isinstance(plan, WaypointPlan):
            xy = np.asarray(plan.xy, dtype=np.float64)
            out.append(np.stack([np.interp(times, t, xy[:, 0]), np.interp(times, t, xy[:, 1])], 1))
        else:
            k = np.clip(np.searchsorted(t, times - 1e-9, side="right") - 1, 0, len(t) - 1)
            sp = np.asarray(plan.speed_mps, dtype=np.float64)[k]
            kc = np.asarray(plan.curvature_1pm, dtype=np.float64)[k]
            sp = np.where(times - 1e-9 < t[0], sp[0], sp)
            out.append(np.stack([sp, kc], 1))
    return tuple(out)


# --- a copy of what What If reads ---------------------------------------------------------------


class LevelCopy(MapLevel):
    """The :data:`SAMPLED_LAYERS` (or the ``layers`` named) of one map level, copied as they are
    now (storage order, with the window's origin), read as the level reads them. ``config``
    is the level's: it names every layer of the level, held here or not.

    A :class:`~maps.level.MapLevel` so that every index transform What If uses is the level's
    own code, not a second copy of it; built without ``MapLevel.__init__``, which would
    allocate every layer and read the tile store. Treat it as read-only: it has no store, and
    the level it came from goes on without it."""

    def __init__(self, level: MapLevel, layers: tuple[str, ...] = SAMPLED_LAYERS) -> None:
        self.config = level.config
        self.size = level.size
        self.resolution_m = level.resolution_m
        self.specs = {name: level.specs[name] for name in layers}
        self.store = None
        # the node writes its layers in place (fusion, terrain, the cost layer, scrolling):
        # only a copy stays as this cycle left it
        self._data = {name: level.storage(name).copy() for name in layers}
        self._fills = [(arr, self.specs[name].fill) for name, arr in self._data.items()]
        self.origin_cell = level.origin_cell

    @property
    def nbytes(self) -> int:
        """Bytes of the copied layers."""
        return sum(a.nbytes for a in self._data.values())


class StackCopy:
    """Levels of a map stack as :class:`LevelCopy` (finest first): the part of
    :class:`~maps.stack.MapStack` What If reads (``levels``, ``level(name)``)."""

    def __init__(self, levels: list[LevelCopy]) -> None:
        self.levels = levels

    level = MapStack.level  # the same lookup, and the same error naming the levels there are


@dataclass(frozen=True)
class WhatIfCopy:
    """What :class:`WhatIf` reads of a KD and a map stack, taken at one moment (between two
    node cycles), so that rollouts can be answered later, in another thread, as they would
    have been then (:meth:`WhatIf.over`).

    ``self_state``: the self entity's current state (None: it has none). The candidates for
    collision checks (:data:`COLLIDING_STATUSES`, object level, world frame, not self), M of
    them in id order: ``positions`` (M, 3) world m, the current positions a KD region query
    tests; ``boxes`` their :class:`~wm.shapes.EntityBoxes` at their states' times with their
    risks; ``state_t_ns`` (M,) int64 those times."""

    stack: StackCopy
    self_id: int | None
    self_state: State | None
    positions: np.ndarray
    boxes: EntityBoxes
    state_t_ns: np.ndarray

    @classmethod
    def of(
        cls,
        kd: kd_store.KnowledgeDatabase,
        stack: MapStack,
        self_id: int | None,
        levels: Iterable[str],
        cols: dict[str, np.ndarray] | None = None,
        copies: Mapping[str, LevelCopy] | None = None,
    ) -> WhatIfCopy:
        """Copy what What If reads of ``kd`` and of ``stack``'s ``levels`` (names; others
        left out); ``cols``: ``kd.current_columns()`` if the caller has taken it already;
        ``copies``: levels copied already, by name, each holding at least
        :data:`SAMPLED_LAYERS` (shared, not copied again). Call it where nothing writes the
        KD or the stack (the node's thread, or its lock)."""
        want, copies = set(levels), copies or {}
        stack_copy = StackCopy([
            copies[lvl.name] if lvl.name in copies else LevelCopy(lvl)
            for lvl in stack.levels if lvl.name in want
        ])  # fmt: skip
        self_state = kd.get(self_id).state if self_id is not None else None
        c = kd.current_columns() if cols is None else cols
        keep = (c["frame"] == "world") & (c["level"] == int(Level.OBJECT))
        keep &= np.isin(c["status"], [s.value for s in COLLIDING_STATUSES])
        if self_id is not None:
            keep &= c["id"] != self_id
        rows = np.flatnonzero(keep)
        rows = rows[np.argsort(c["id"][rows], kind="stable")]  # the KD's region order
        frames = [kd.get(int(i)) for i in c["id"][rows]]
        boxes, t_ns = _boxes_and_times(kd, frames)
        return cls(stack_copy, self_id, self_state, c["position"][rows], boxes, t_ns)

    @property
    def nbytes(self) -> int:
        """Bytes of the copied map layers (the entities' arrays are small beside them)."""
        return sum(lvl.nbytes for lvl in self.stack.levels)

    def candidates(self, xy: np.ndarray, radius_m: float) -> tuple[EntityBoxes, np.ndarray]:
        """The candidates within ``radius_m`` of world ``xy`` (the KD's circle test on their
        current positions), as :func:`_boxes_and_times` gives them."""
        region = kd_store.Circle("world", (float(xy[0]), float(xy[1])), float(radius_m))
        kd_store.spatial.check_region(region)  # the KD refuses a region that is not finite
        sel = np.flatnonzero(region.contains(self.positions))
        b = self.boxes
        boxes = EntityBoxes(b.ids[sel], b.centers_xyz[sel], b.sizes_lwh[sel], b.yaws[sel],
                            b.velocities_xyz[sel], b.risks[sel])  # fmt: skip
        return boxes, self.state_t_ns[sel]


def _boxes_and_times(
    kd: kd_store.KnowledgeDatabase, frames: list[kd_store.EntityFrame]
) -> tuple[EntityBoxes, np.ndarray]:
    """The boxes of ``frames`` with their risks (value judgment) and, aligned with them, the
    times (int64 ns) of the states they stand at."""
    risks = [entity_value(kd, f).risk for f in frames]
    boxes = boxes_of(frames, risks)
    kept = [f.state.t_ns for f in frames if f.state is not None and f.state.frame == "world"]
    return boxes, np.array(kept, dtype=np.int64).reshape(len(boxes))


def _moved_to(boxes: EntityBoxes, state_t_ns: np.ndarray, t_ns: int) -> EntityBoxes:
    """``boxes`` at time ``t_ns`` (int64 ns): each moved from its state's time at its constant
    velocity (states may be older than a rollout's start)."""
    if not len(boxes):
        return boxes
    dt = (int(t_ns) - state_t_ns) * 1e-9
    c = boxes.centers_xyz + dt[:, None] * boxes.velocities_xyz
    return EntityBoxes(boxes.ids, c, boxes.sizes_lwh, boxes.yaws, boxes.velocities_xyz,
                       boxes.risks)  # fmt: skip


# --- What If -----------------------------------------------------------------------------------


class WhatIf:
    """The What If interface over a KD and a map stack (module docstring), or over a copy of
    what it reads of them (:meth:`over`).

    What If is built from the engine configuration ``config`` (a bare NodeConfig or None: the
    other sections' defaults) and keeps of it: ``config``, its ``whatif`` section (each level's
    step); ``vehicle``, the vehicle model (``node.vehicle``); ``horizons_s``, each level's
    planning horizon in s (``kd.memory.horizons_s``, as long as the KD's short-term memory at
    the level). ``self_id`` is the KD entity of the vehicle itself (left out of collision
    checks and used as the default start)."""

    def __init__(
        self,
        kd: kd_store.KnowledgeDatabase,
        stack: MapStack,
        config: EngineConfig | NodeConfig | None = None,
        self_id: int | None = None,
    ) -> None:
        from wm.engine_config import EngineConfig

        if isinstance(config, WhatIfConfig):
            raise TypeError(
                "WhatIf takes the engine configuration (EngineConfig), not its whatif section: "
                "the vehicle is node.vehicle and the horizons kd.memory.horizons_s"
            )
        engine = EngineConfig.of(config)
        self.kd, self.stack = kd, stack
        self.config: WhatIfConfig = engine.whatif
        self.vehicle: VehicleConfig = engine.node.vehicle
        self.horizons_s: Mapping[str, float] = engine.kd.memory.horizons_s
        self.self_id = self_id
        f = self.vehicle.footprint_samples
        u = np.linspace(-0.5, 0.5, f[0]) * self.vehicle.length_m
        w = np.linspace(-0.5, 0.5, f[1]) * self.vehicle.width_m
        U, W = np.meshgrid(u, w, indexing="ij")
        self._foot = np.stack([U.ravel(), W.ravel()], 1)  # (F, 2) body-frame offsets
        self.copy: WhatIfCopy | None = None

    @classmethod
    def over(cls, copy: WhatIfCopy, config: EngineConfig | NodeConfig | None = None) -> WhatIf:
        """What If reading ``copy`` instead of a KD and a stack: its answers are those
        ``WhatIf(kd, stack, config, self_id)`` gave when the copy was taken (for the levels
        copied)."""
        wi = cls(None, copy.stack, config, copy.self_id)  # type: ignore[arg-type]
        wi.copy = copy
        return wi

    def start_from_kd(self) -> Start:
        """The vehicle's current state from the KD's ``self`` entity."""
        if self.self_id is None:
            raise WhatIfError("no start given and no self entity to take it from")
        s = self.copy.self_state if self.copy is not None else self.kd.get(self.self_id).state
        if s is None:
            raise WhatIfError(f"self entity {self.self_id} has no state yet")
        from core.geometry import quat_to_matrix, yaw_of

        yaw = yaw_of(quat_to_matrix(s.orientation_xyzw))
        speed = float(np.hypot(*s.velocity_xyz[:2]))
        return Start(s.position_xyz[:2].copy(), yaw, speed, s.t_ns)

    def simulate(
        self,
        plans: list[Plan],
        *,
        level: str = "subsystem",
        start: Start | None = None,
        horizon_s: float | None = None,
        entities: EntityBoxes | None = None,
    ) -> WhatIfResult:
        """Roll out every plan at ``level`` from ``start`` (default: the KD's self state) for
        ``horizon_s`` (default: the level's horizon) against the maps and ``entities`` (default:
        the KD's object entities near enough to matter)."""
        cfg = self.config
        if level not in cfg.steps_s or level not in [lv.name for lv in self.stack.levels]:
            have = [lv.name for lv in self.stack.levels if lv.name in cfg.steps_s]
            raise WhatIfError(f"level {level!r} does not exist; levels: {have}")
        if not plans:
            raise WhatIfError("simulate needs at least one plan")
        for i, p in enumerate(plans):
            if not isinstance(p, WaypointPlan | ControlPlan):
                raise WhatIfError(f"plan {i}: not a WaypointPlan or ControlPlan: {type(p)}")
            check_plan(p, i)
        start = start or self.start_from_kd()
        dt = cfg.steps_s[level]
        horizon = self.horizons_s[level] if horizon_s is None else float(horizon_s)
        if not (np.isfinite(horizon) and horizon > 0):
            raise WhatIfError(f"horizon_s must be > 0 s, got {horizon_s!r}")
        n = max(1, round(horizon / dt))
        times = dt * np.arange(1, n + 1)
        xy, yaw, v, lim = self._roll(plans, start, n, dt, times)
        t_s = np.concatenate([[0.0], times])
        res = self._sample_maps(level, xy, yaw)
        if entities is None:
            reach = self.vehicle.max_speed_mps * horizon + cfg.entity_search_margin_m
            entities = self.entities_near(start.xy, reach, start.t0_ns)
        col = self._collisions(xy, yaw, t_s, start, entities)
        step = np.diff(xy, axis=1)
        return WhatIfResult(
            level=level, t0_ns=start.t0_ns, dt_s=dt, t_s=t_s, xy=xy, yaw=yaw, speed=v, **res,
            **col, distance_m=np.hypot(step[..., 0], step[..., 1]).sum(1), limited_steps=lim,
            names=[p.name for p in plans],
        )  # fmt: skip

    def _roll(self, plans, start, n, dt, times):
        veh = self.vehicle
        wanted = _wanted(plans, times)
        is_wp = np.array([isinstance(p, WaypointPlan) for p in plans])
        P = len(plans)
        xy, yaw = np.empty((P, n + 1, 2)), np.empty((P, n + 1))
        v, lim = np.empty((P, n + 1)), np.zeros(P, np.int64)
        for mask in (is_wp, ~is_wp):
            idx = np.flatnonzero(mask)
            if not len(idx):
                continue
            w = np.stack([wanted[i] for i in idx])
            if mask is is_wp:
                out = rollout(start, n, dt, veh, target_xy=w)
            else:
                out = rollout(start, n, dt, veh, speed_want=w[..., 0], curv_want=w[..., 1])
            xy[idx], yaw[idx], v[idx], lim[idx] = out
        return xy, yaw, v, lim

    def footprint_xy(self, xy: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        """World points (..., F, 2) of the footprint samples at poses xy (..., 2), yaw (...)."""
        c, s = np.cos(yaw)[..., None], np.sin(yaw)[..., None]
        u, w = self._foot[:, 0], self._foot[:, 1]
        return np.stack([xy[..., None, 0] + c * u - s * w, xy[..., None, 1] + s * u + c * w], -1)

    def _sample_maps(self, level: str, xy: np.ndarray, yaw: np.ndarray) -> dict[str, np.ndarray]:
        lvl = self.stack.level(level)
        pts = self.footprint_xy(xy, yaw)
        shape = pts.shape[:-1]
        flat = pts.reshape(-1, 2)
        rows, cols, inside = lvl.world_to_window(flat)
        srow, scol = lvl.window_to_storage(rows[inside], cols[inside])

        def read(layer: str) -> np.ndarray:
            out = np.full(len(flat), np.nan, dtype=np.float64)
            out[inside] = lvl.storage(layer)[srow, scol]
            return out.reshape(shape)

        elev = read("elevation")
        unknown = ~np.isfinite(elev)
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                return {
                    "elevation": np.nanmean(elev, axis=-1),
                    "slope": np.nanmax(read("slope"), axis=-1),
                    "traversability": np.nanmin(read("traversability"), axis=-1),
                    "cost": np.nanmax(read("cost"), axis=-1),
                    "unknown_fraction": unknown.mean(axis=-1),
                }

    def entities_near(self, xy: np.ndarray, radius_m: float, t_ns: int) -> EntityBoxes:
        """Object-level entities (not denied or gone, not self) within ``radius_m`` of ``xy``,
        at their positions as of ``t_ns`` (constant velocity from their states)."""
        if self.copy is not None:
            boxes, state_t_ns = self.copy.candidates(xy, radius_m)
        else:
            region = kd_store.Circle("world", (float(xy[0]), float(xy[1])), float(radius_m))
            ids = self.kd.region(region, statuses=list(COLLIDING_STATUSES), levels=[Level.OBJECT])
            frames = [self.kd.get(int(i)) for i in ids if int(i) != self.self_id]
            boxes, state_t_ns = _boxes_and_times(self.kd, frames)
        return _moved_to(boxes, state_t_ns, t_ns)

    def _collisions(
        self, xy: np.ndarray, yaw: np.ndarray, t_s: np.ndarray, start: Start, ents: EntityBoxes
    ) -> dict[str, np.ndarray]:
        P, S1 = xy.shape[:2]
        none = {
            "clearance_m": np.full((P, S1), np.inf),
            "nearest_entity": np.full((P, S1), -1, np.int64),
            "entity_risk": np.zeros((P, S1)),
            "min_clearance_m": np.full(P, np.inf),
            "collision_entity": np.full(P, -1, np.int64),
            "collision_t_s": np.full(P, np.nan),
        }
        if not len(ents):
            return none
        veh = self.vehicle
        r_veh = 0.5 * np.hypot(veh.length_m, veh.width_m)
        c = ents.at(t_s)[..., :2]  # (S1, M, 2) predicted centres
        d = np.linalg.norm(xy[:, :, None, :] - c[None], axis=-1)  # (P, S1, M)
        lb = d - r_veh - ents.radii_m[None, None, :]
        j = np.argmin(lb, axis=-1)
        clearance = np.take_along_axis(lb, j[..., None], -1)[..., 0]
        out = {
            "clearance_m": clearance,
            "nearest_entity": ents.ids[j],
            "entity_risk": ents.risks[j],
        }
        out.update(self._narrowphase(xy, yaw, t_s, c, lb, clearance, ents))
        return out

    def _narrowphase(self, xy, yaw, t_s, c, lb, clearance, ents) -> dict[str, np.ndarray]:
        """fcl on the pairs whose circles meet (first collision in time), and the least
        clearance of each plan refined with fcl where it is small."""
        import fcl

        veh = self.vehicle
        P = xy.shape[0]
        car = fcl.CollisionObject(fcl.Box(veh.length_m, veh.width_m, veh.height_m))
        objs = [fcl.CollisionObject(fcl.Box(*map(float, s))) for s in ents.sizes_lwh]

        def place(o, p, th) -> None:
            R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
            o.setTransform(fcl.Transform(R, np.array([p[0], p[1], 0.0])))

        first_e = np.full(P, -1, np.int64)
        first_t = np.full(P, np.nan)
        hits = np.argwhere(lb < 0)  # (k, 3) plan, step, entity; row-major: time order per plan
        done = np.zeros(P, bool)
        req = fcl.CollisionRequest()
        for p, s, m in hits:
            if done[p]:
                continue
            place(car, xy[p, s], yaw[p, s])
            place(objs[m], c[s, m], ents.yaws[m])
            if fcl.collide(car, objs[m], req, fcl.CollisionResult()):
                done[p], first_e[p], first_t[p] = True, ents.ids[m], t_s[s]
        least = clearance.min(axis=1)
        refined = least.copy()
        for p in np.flatnonzero(~done & (least < self.config.clearance_refine_m)):
            s = int(np.argmin(clearance[p]))
            m = int(np.argmin(lb[p, s]))
            place(car, xy[p, s], yaw[p, s])
            place(objs[m], c[s, m], ents.yaws[m])
            refined[p] = fcl.distance(car, objs[m], fcl.DistanceRequest(), fcl.DistanceResult())
        refined[done] = 0.0
        return {"min_clearance_m": refined, "collision_entity": first_e, "collision_t_s": first_t}
