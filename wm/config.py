"""Typed configuration of the world-modeling node, with every default in one place.

Levels are the map levels of docs/architecture.md, map levels and tiles (reference 000,
Table 2): ``primitive`` (0.04 m), ``subsystem`` (0.4 m), ``vehicle`` (4 m), ``section`` (30 m).
Each node level runs its slow work (terrain, value-judgment cost layer) at its own period:
"the coarse levels need not run every sensor frame" (reference 001, 4.4.10: the planning
horizon and replanning interval grow by about an order of magnitude per level).

The root of a run's configuration, with the subsystems the node builds, is
:class:`wm.engine_config.EngineConfig`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum

from core.errors import EngineError


class NodeSettingError(EngineError, ValueError):
    """A node, planner or What If setting out of its range; names the setting and value."""


#: Map levels the node runs, finest first, and the period (s) of each level's slow work.
DEFAULT_LEVEL_PERIODS_S: dict[str, float] = {
    "primitive": 0.2,
    "subsystem": 0.5,  # as often as the subsystem planner replans (PlannerConfig)
    "vehicle": 1.0,
    "section": 5.0,
}

#: Step (s) of What If rollouts per level; a rollout lasts the level's planning horizon, which
#: is the KD's (``kd_store.config.DEFAULT_HORIZONS_S``: reference 001, 4.1, the subsystem level
#: plans about 5 s ahead, the vehicle level about a minute).
DEFAULT_STEPS_S: dict[str, float] = {
    "primitive": 0.05,
    "subsystem": 0.1,
    "vehicle": 1.0,
    "section": 10.0,
}


class PoseSource(StrEnum):
    """Where the node takes the vehicle pose from."""

    ODOMETRY = "odometry"  # LADAR odometry fused with wheel odometry (sp.odometry)
    TRUTH = "truth"  # the log's ground-truth pose (simulated logs, evaluation)


@dataclass(frozen=True)
class PredictionConfig:
    """Short-term expectations and the predicted range image (reference 001, 4.2 item 2).

    expectation_steps_s: times ahead (s) of each entity's expected states (the first beyond
                         the next sweep, so SP's next observation does not meet them).
    range_image_every:   ray-cast a predicted range image every this many sweeps (0: never).
    range_image_hw:      its (rows, columns) on the egosphere (a coarse copy of the sensor's).
    mismatch_m:          an observed range differing by more than this from the prediction
                         counts as a surprise; surprises feed next cycle's attention.
    """

    expectation_steps_s: tuple[float, ...] = (0.25, 0.5, 1.0)
    expect_min_confidence: float = 0.5  # hypotheses below this get no expectations
    range_image_every: int = 10
    range_image_hw: tuple[int, int] = (32, 256)
    mismatch_m: float = 1.0
    max_attention_points: int = 256


@dataclass(frozen=True)
class VehicleConfig:
    """The vehicle: footprint (m) and limits (SI units). Set once, as ``node.vehicle``; What If
    rolls plans out with it (:class:`wm.whatif.WhatIf`)."""

    length_m: float = 4.5
    width_m: float = 2.0
    height_m: float = 1.8
    max_speed_mps: float = 15.0
    max_accel_mps2: float = 3.0
    max_decel_mps2: float = 6.0
    max_curvature_1pm: float = 0.2  # 5 m turning radius
    max_yaw_rate_rps: float = 1.0
    footprint_samples: tuple[int, int] = (3, 3)  # points along length x width


@dataclass(frozen=True)
class VJConfig:
    """Value judgment weights (reference 001, 4.3). Costs and risks are dimensionless.

    cost layer: w_traversability * (1 - traversability)
                + w_uncertainty * min(1, sqrt(elevation_var) / sigma_ref_m), w_unknown where the
                elevation is unknown; plus a labelled entity's cost (its class value's) times the
                confidence in it (wm.vj.confidence).
    plan evaluation: cost = sum over steps of (map cost + w_time) * dt; risk = collision_risk on a
    collision, else max over steps of entity risk * exp(-clearance / clearance_scale_m);
    benefit = w_progress * progress towards the goal (m).
    attention priority: w_proximity / (1 + d/proximity_scale_m) + w_danger * risk
                        + w_novelty * (not confirmed) + w_relevance * (near the plan).
    """

    w_traversability: float = 1.0
    w_unknown: float = 0.5
    w_uncertainty: float = 0.2
    sigma_ref_m: float = 0.5
    w_time: float = 0.1
    collision_risk: float = 100.0
    clearance_scale_m: float = 1.0
    w_progress: float = 1.0
    w_proximity: float = 1.0
    proximity_scale_m: float = 10.0
    w_danger: float = 1.0
    w_novelty: float = 0.5
    w_relevance: float = 1.0
    relevance_radius_m: float = 3.0
    attention_size: int = 16


@dataclass(frozen=True)
class PlannerConfig:
    """The behavior-generation consumer at one level (reference 001, 4.1).

    replan_period_s: a new plan every this many seconds (4.1.7: about a tenth of the horizon).
    speeds_mps, curvatures_1pm: the fan of tentative plans, every (speed m/s, curvature 1/m)
                     pair held over the horizon, hypothesized slowest first (so the slowest
                     plans, the fallback when nothing is safe, are in the first batch).
    min_clearance_m: plans passing closer than this (m) to an entity count as unsafe.
    batch_size:      tentative plans simulated per What If call.
    budget_s:        the planning period's time budget (s, wall clock): after it no further
                     batch is hypothesized and the best plan so far is kept (the first batch
                     always runs). 100 plans take about 15 ms on the default maps.
    """

    level: str = "subsystem"
    replan_period_s: float = 0.5
    speeds_mps: tuple[float, ...] = (0.0, 2.0, 4.0, 6.0, 8.0, 10.0)
    curvatures_1pm: tuple[float, ...] = (-0.15, -0.1, -0.06, -0.03, 0.0, 0.03, 0.06, 0.1, 0.15)
    min_clearance_m: float = 0.5
    batch_size: int = 18
    budget_s: float = 0.2

    def __post_init__(self) -> None:
        b = self.budget_s
        if not (isinstance(b, int | float) and 0 < b < float("inf")):  # NaN fails too
            raise NodeSettingError(f"PlannerConfig.budget_s must be a finite time > 0 s, got {b!r}")
        if not (isinstance(self.batch_size, int) and self.batch_size >= 1):
            raise NodeSettingError(
                f"PlannerConfig.batch_size must be an int >= 1, got {self.batch_size!r}"
            )
        if not self.speeds_mps or not self.curvatures_1pm:
            raise NodeSettingError(
                f"PlannerConfig needs at least one speed and one curvature, got speeds_mps="
                f"{self.speeds_mps!r}, curvatures_1pm={self.curvatures_1pm!r}"
            )


@dataclass(frozen=True)
class NodeConfig:
    """The node cycle (docs/architecture.md, the node cycle)."""

    pose_source: PoseSource = PoseSource.ODOMETRY
    level_periods_s: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_LEVEL_PERIODS_S))
    deskew_bins: int = 8  # pose slices per sweep when moving points to the world
    kd_advance_every: int = 10  # trim short-term memory every this many sweeps
    kd_flush_every_ns: int = 1_000_000_000  # long-term memory to the file this often (log time)
    kd_tile_flush_every_ns: int = 10_000_000_000  # ... map tiles with it this often
    # a read-only copy of the KD file published here after a flush (None: none), for other
    # processes to open while the node writes the KD (KnowledgeDatabase.publish_snapshot)
    snapshot_path: str | None = None
    snapshot_every_s: float = 5.0  # ... at most this often (s of log time), and at the end
    prediction: PredictionConfig = field(default_factory=PredictionConfig)
    vj: VJConfig = field(default_factory=VJConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)  # What If's vehicle model too
    use_sp: bool = True  # run SP levels 2..5 (off: maps, odometry and predictions only)
    # the map level whose ground heights SP is given as the ground it should expect
    # (sp.ground_prior; None: none)
    ground_prior_level: str | None = "subsystem"
    odometry_process: bool = True  # register sweeps in a child process, one sweep ahead
    # sweeps the odometry process may have in hand: with two, a registration that runs late
    # (the process shares its core with the log's decoder) does not stall the node, for one
    # more sweep (0.1 s at 10 Hz) of latency
    odometry_ahead: int = 2
    # a sweep waits for wheel odometry past its end at most this long (ns of log time)
    wheel_wait_ns: int = 200_000_000
    # a frame stamped more than this after the log's latest frame, or before it, is held back,
    # not taken (a corrupted stamp would otherwise carry the self pose and every state far
    # into the future, or make every later frame look out of order)
    max_time_jump_ns: int = 600_000_000_000
    # ... once the log's rhythm is known, this many median gaps between its frames, but at
    # least min_time_jump_ns (max_time_jump_ns caps both): a recording paused for seconds
    # starts a new segment (nothing integrates across the pause) and one stamp a minute ahead
    # costs no minute of frames
    time_jump_gaps: float = 50.0
    min_time_jump_ns: int = 2_000_000_000
    # ... and this many such frames in a row, each within max_time_jump_ns of the one before,
    # are a real jump of the log's clock (the recording paused, or its clock restarted
    # earlier): the node starts a new segment there and takes them; fewer, followed by a frame
    # in time, were corrupted stamps and are skipped
    segment_confirm_frames: int = 3
    # BLAS and OpenMP threads in the node's process during a run (None: the libraries' own
    # choice). One: the node's array operations are small, and the libraries' idle threads
    # spin on the core the odometry process needs, slowing both processes
    compute_threads: int | None = 1

    def __post_init__(self) -> None:
        def need(ok: bool, what: str, value: object) -> None:
            if not ok:
                raise NodeSettingError(f"NodeConfig.{what}, got {value!r}")

        need(
            isinstance(self.odometry_ahead, int) and self.odometry_ahead >= 1,
            "odometry_ahead must be an int >= 1",
            self.odometry_ahead,
        )
        need(
            math.isfinite(self.snapshot_every_s) and self.snapshot_every_s >= 0,
            "snapshot_every_s must be a finite number >= 0 (s)",
            self.snapshot_every_s,
        )
        need(
            isinstance(self.segment_confirm_frames, int) and self.segment_confirm_frames >= 2,
            "segment_confirm_frames must be an int >= 2",
            self.segment_confirm_frames,
        )
        need(
            math.isfinite(self.time_jump_gaps) and self.time_jump_gaps > 0,
            "time_jump_gaps must be a finite number > 0",
            self.time_jump_gaps,
        )
        need(self.min_time_jump_ns > 0 and self.max_time_jump_ns > 0,
             "min_time_jump_ns and max_time_jump_ns must be > 0 (ns)",
             (self.min_time_jump_ns, self.max_time_jump_ns))  # fmt: skip


@dataclass(frozen=True)
class WhatIfConfig:
    """What If rollouts: each level's step (s), and how far entities and clearances are
    looked at (m). The vehicle model and each level's horizon are set once elsewhere, where
    What If reads them: ``node.vehicle`` and ``kd.memory.horizons_s`` of the engine
    configuration (:class:`wm.engine_config.EngineConfig`) it is built from."""

    steps_s: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_STEPS_S))
    entity_search_margin_m: float = 20.0  # entities this far beyond the reachable disc ignored
    clearance_refine_m: float = 3.0  # refine a plan's least clearance with fcl below this
