"""The world-modeling node: one cycle per LADAR sweep (docs/architecture.md, the node cycle).

Per sweep, in the order of docs/architecture.md, the node cycle, and reference 001, 4.2 (the WM
keeps the KD current, ``KD(t) = KD(t-1) + Observation(t)``) and 4.5 (SP at every level):

1. pose: LADAR odometry fused with wheel odometry (sp.odometry), or the log's ground truth;
   odometry never reads ground truth: its world starts at the first sweep, level with gravity
   (:func:`initial_pose` from wheel odometry, else :func:`level_from_ground`), so scorers
   align estimates to truth themselves; the sweep is deskewed into the world with the pose at
   each slice's time, once, for the maps and SP. By default the odometry runs in its own
   process (wm.odometry_worker), ``NodeConfig.odometry_ahead`` sweeps ahead of the rest;
2. self state into the KD (entity ``self``, world frame);
3. maps: every level scrolls to the new pose and fuses the points (maps.stack);
4. SP levels 1..5 (sp.pipeline) observe the sweep: entities, their states, classes,
   relations and events (sp.observations), and their labels into the map layers; attention
   comes from last cycle's prediction surprises; then the entity update (wm.entities) writes
   SP's observations into the KD as entity frames, states, relations and event frames;
5. each map level's slow work at its own period: terrain (slope, traversability), the
   value-judgment cost layer and the level's entities-of-attention list (4.3, 4.4.11), which
   weighs relevance to the controller's current plan when told it (:meth:`set_plan`);
6. predictions for the next cycle (4.2 item 2): expected entity states and, every few
   sweeps, a predicted range image compared with the next observed one.

Sweeps wait until the log has passed their last point's time, so the poses (odometry or truth)
covering them have arrived; :meth:`WorldModelNode.finish` drains the rest at the end and
flushes the KD file. Used as a context manager (``with WorldModelNode(kd) as node:``) the node
finishes when the block ends, and an error inside the block still flushes what the KD holds
and stops the odometry process before it propagates.

Time jumps: a frame stamped more than :meth:`WorldModelNode.jump_bound_ns` after the log's
latest one, or that far before it, is held back (the bound follows the log's rhythm: 50 median
gaps between frames, 2 s at least, ``NodeConfig.max_time_jump_ns`` at most). A frame in time
after it shows it was a corrupted stamp: it is skipped (``stats.skipped["time jump"]``).
``segment_confirm_frames`` such frames in a row, each within the bound of the one before, are
a real jump of the log's clock: a gap
forward (the recording paused) or back (the clock restarted earlier and runs on from there).
Either way the node ends the segment before the jump (its sweeps run, the KD is flushed),
starts a new one (``stats.events["time_jump_new_segment"]``, a note saying which way it
jumped) and takes the held frames; after a jump back the time-order checks start anew, so the
frames of the new segment are not taken for stragglers. Nothing integrates across the jump:
the odometry starts again from the last pose before it (a fresh registration map and wheel
history, zero velocity), the pose track and the range-image prediction start empty. SP's
tracks are kept; their prediction uncertainty grows with the gap like any other interval, so
static objects keep their entities and movers are found anew.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import typing
from collections import Counter, defaultdict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import kd_store
from core.errors import EngineError
from core.geometry import (
    BODY,
    CAMERA,
    LADAR,
    check_pose,
    matrix_to_quat,
    matrix_to_rpy,
    mount_of,
    rpy_to_matrix,
    se3,
)
from kd_store import Level, State, Status
from logs.types import (
    CameraFrame,
    GroundTruthPose,
    LadarScan,
    LogMessage,
    ObjectBoxes,
    OdometryFrame,
    TransformFrame,
)
from maps.stack import MapStack
from maps.terrain import update_terrain
from sp.ground_prior import GroundPrior
from sp.odometry import OdometryError
from sp.pipeline import SensoryProcessor, SPResult
from wm import predict, vj
from wm.config import NodeConfig, PoseSource
from wm.engine_config import EngineConfig
from wm.entities import EntityUpdater
from wm.odometry_worker import OdometryReply, OdometryWorker
from wm.poses import PoseError, PoseTrack, deskew_to_world
from wm.screen import check_frame, finite_points
from wm.truth import truth_boxes_to_world
from wm.whatis import WhatIs

log = logging.getLogger(__name__)
#: gaps between frames the node learns before it bounds time jumps by them, and relearns after
_GAPS_NEEDED = 16


def initial_pose(wheel: OdometryFrame) -> np.ndarray:
    """The body pose the estimated world starts from (4x4 float64): the first wheel-odometry
    message's roll and pitch (the gravity direction an inertial unit measures), with zero yaw
    and position, so the world frame is z up without reading any ground-truth topic; a
    message whose rotation is not a rotation gives the identity."""
    T = np.asarray(wheel.T_parent_child, dtype=np.float64)
    try:
        check_pose(T, "first wheel odometry pose")
    except ValueError:
        return np.eye(4)
    roll, pitch, _ = matrix_to_rpy(T[:3, :3])
    return se3(rpy_to_matrix(roll, pitch, 0.0))


def level_from_ground(
    points_xyz: np.ndarray,
    T_body_ladar: np.ndarray,
    cell_m: float = 2.0,
    ring_m: tuple[float, float] = (3.0, 30.0),
    min_cells: int = 20,
    max_rms_m: float = 0.1,
    max_tilt_rad: float = 0.26,
) -> np.ndarray | None:
    """The body's roll and pitch from the ground under it (4x4 float64, zero yaw and position),
    for a log with no attitude (no wheel odometry or inertial unit): the lowest return of each
    ``cell_m`` cell between ``ring_m`` metres (body xy) is taken as ground, a plane is fitted to
    them by least squares twice (dropping cells over 0.15 m off the first fit), and the body is
    turned so that its normal is up. None when fewer than ``min_cells`` cells fit, their RMS is
    over ``max_rms_m`` (no flat ground to trust) or the tilt is over ``max_tilt_rad``.
    points_xyz (N, 3) in the LADAR frame, metres."""
    pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)] @ T_body_ladar[:3, :3].T + T_body_ladar[:3, 3]
    r = np.hypot(pts[:, 0], pts[:, 1])
    pts = pts[(r >= ring_m[0]) & (r <= ring_m[1])]
    if len(pts) < min_cells:
        return None
    cell = np.floor(pts[:, :2] / cell_m).astype(np.int64)
    key = cell[:, 0] * 100_003 + cell[:, 1]
    order = np.lexsort((pts[:, 2], key))
    first = np.r_[True, key[order][1:] != key[order][:-1]]
    low = pts[order[first]]
    keep = np.ones(len(low), dtype=bool)
    for _ in range(2):
        if keep.sum() < min_cells:
            return None
        A = np.column_stack([low[keep, :2], np.ones(int(keep.sum()))])
        coef = np.linalg.lstsq(A, low[keep, 2], rcond=None)[0]
        resid = low[:, 2] - np.column_stack([low[:, :2], np.ones(len(low))]) @ coef
        keep = np.abs(resid) <= 0.15
    if keep.sum() < min_cells or np.sqrt(np.mean(resid[keep] ** 2)) > max_rms_m:
        return None
    n = np.array([-coef[0], -coef[1], 1.0]) / np.hypot(np.hypot(coef[0], coef[1]), 1.0)
    roll = float(np.arctan2(n[1], n[2]))
    pitch = float(np.arctan2(-n[0], np.hypot(n[1], n[2])))
    if max(abs(roll), abs(pitch)) > max_tilt_rad:
        return None
    return se3(rpy_to_matrix(roll, pitch, 0.0))


class NodeError(EngineError, ValueError):
    """The node cannot run on what it was given (names what is missing and where)."""


class FrameTypeError(EngineError, TypeError):
    """:meth:`WorldModelNode.feed` was given something that is not a log frame (names its
    type and the frame types the node takes)."""


FRAME_TYPES: tuple[type, ...] = typing.get_args(LogMessage)


@dataclass
class CycleResult:
    """What one cycle did: its time, pose, points fused and SP output (or None)."""

    t_ns: int
    T_world_body: np.ndarray  # at t_pose_ns, the sweep's middle
    n_points: int
    t_pose_ns: int
    sp_result: Any | None = None
    odometry_status: str = ""


@dataclass
class NodeStats:
    """Counters, per-stage wall times (s) and per-stage CPU times (s, the node's thread; the
    ``odometry`` entry is the odometry process's CPU when it runs in one) over a run."""

    frames: Counter = field(default_factory=Counter)
    sweeps: int = 0
    stage_s: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    stage_cpu_s: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    odometry_status: Counter = field(default_factory=Counter)
    skipped: Counter = field(default_factory=Counter)  # frames refused by feed, per reason
    # points dropped from sweeps the node took: non-finite or beyond the screen's range
    dropped_nonfinite_points: int = 0
    # what the node did about the log on its own, per named reason (time_jump_new_segment)
    events: Counter = field(default_factory=Counter)
    notes: list[str] = field(default_factory=list)
    kd_flushes: int = 0  # KD flushes to the file, periodic and final
    # the longest the KD file stayed behind the log: log time (newest frame) minus the sweep
    # time of the last flush (or the log's start before the first), ns, just before a flush
    kd_flush_max_lag_ns: int = 0
    # read-only snapshots of the KD file published (NodeConfig.snapshot_path): the wall time
    # of each (ms: flush, checkpoint, copy, rename), and how many failed (logged; the run goes on)
    snapshot_ms: list[float] = field(default_factory=list)
    snapshot_failures: int = 0
    range_image_error_m: list[float] = field(default_factory=list)
    surprise_fraction: list[float] = field(default_factory=list)


class _StageClock:
    """Adds each stage's wall time (perf_counter) and this thread's CPU time (thread_time)
    to the node's stats."""

    def __init__(self, stats: NodeStats) -> None:
        self.stats = stats
        self.wall, self.cpu = time.perf_counter(), time.thread_time()

    def lap(self, name: str) -> None:
        wall, cpu = time.perf_counter(), time.thread_time()
        self.stats.stage_s[name] += wall - self.wall
        self.stats.stage_cpu_s[name] += cpu - self.cpu
        self.wall, self.cpu = wall, cpu


class WorldModelNode:
    """Keeps the KD and the map stack current from a stream of log frames (module docstring)."""

    def __init__(
        self,
        kd: kd_store.KnowledgeDatabase,
        config: EngineConfig | NodeConfig | None = None,
        stack: MapStack | None = None,
    ) -> None:
        self.kd = kd
        # the whole configuration (a bare NodeConfig: default SP, odometry and maps), and
        # its node section, which the cycle reads
        self.engine_config = EngineConfig.of(config)
        self.config = self.engine_config.node
        self.stack = stack if stack is not None else MapStack(self.engine_config.maps)
        self.stats = NodeStats()
        # SP is given the class library and the KD's id source; the node alone writes the KD
        self.sp = (
            SensoryProcessor(kd.classes, kd.new_id, self.engine_config.sp)
            if self.config.use_sp
            else None
        )
        self.entities = EntityUpdater(kd)
        if self.config.ground_prior_level is not None:  # names the levels when it is none
            self.stack.level(self.config.ground_prior_level)
        if self.sp is None:
            self.stats.notes.append("SP levels 2..5 off (NodeConfig.use_sp)")
        self.T_body_ladar: np.ndarray | None = None  # fixed by the first sweep
        self.T_body_camera: np.ndarray | None = None
        self.mounts: dict[str, np.ndarray] = {}  # child frame -> T_body_child, from /tf
        self._body_to_ladar = False  # sweeps come in base_link and go into the ladar mount
        self.truth = PoseTrack()
        self.track = PoseTrack()  # the poses the node uses (estimated, or truth)
        self.odometry: Any | None = None
        # where the odometry's world starts: level with gravity, never from ground truth
        self.T_world_body0: np.ndarray | None = None
        self.last_wheel_t_ns: int | None = None
        self.last_sweep_t_ns: int | None = None  # the newest sweep taken
        self._flushed_ns: int | None = None  # log time of the last KD flush
        self._log_start_ns: int | None = None  # the first frame taken: the lag's origin
        self._flushed_at: tuple[int, int | None] | None = None  # (sweeps, last_t_ns) flushed
        self._tiles_ns: int | None = None  # ... and of the last one with map tiles
        self._snapshot_ns: int | None = None  # ... and of the last snapshot published
        if self.config.snapshot_path is not None:  # refused now, not after a run's work
            kd.snapshot_target(self.config.snapshot_path)
        self.pending: deque[LadarScan] = deque()
        self.inflight: deque[tuple[LadarScan, CameraFrame | None]] = deque()  # at the odometry
        self.camera: CameraFrame | None = None
        self.truth_boxes: ObjectBoxes | None = None
        self.last_t_ns: int | None = None
        # messages beyond a time jump, not taken yet (module docstring)
        self.held: list[LogMessage] = []
        self._gaps: deque[int] = deque(maxlen=4 * _GAPS_NEEDED)  # ns between taken frames
        self._n_gaps = 0
        self._jump_bound_ns: int | None = None  # jump_bound_ns, once learnt
        self.level_due_ns = {lvl.name: -(2**62) for lvl in self.stack.levels}
        self.attention_world_xyz: np.ndarray | None = None
        self.plan_xy: np.ndarray | None = None  # the controller's current plan (set_plan)
        self.prediction: predict.RangePrediction | None = None
        self.surprises = predict.SurpriseEvents()
        # called with each cycle's result at its end, in the node's thread (a server's push
        # stream); a listener must be quick and must not raise: the node waits for it
        self.cycle_listeners: list[Callable[[CycleResult], None]] = []
        self.self_id = kd.add_entity(
            "self",
            Level.OBJECT,
            generic_classes=("vehicle",),
            status=Status.CONFIRMED,
            confidence=1.0,
            noteworthy=True,
        ).id

    # --- frames in -------------------------------------------------------------------------

    def __enter__(self) -> WorldModelNode:
        return self

    def __exit__(self, et: type[BaseException] | None, e: BaseException | None, tb: Any) -> None:
        """A clean exit finishes (the last sweeps run, the KD file flushed, the odometry
        stopped); an error flushes what the KD holds and stops the odometry, then propagates."""
        if et is None:
            self.finish()
            return
        try:
            self.flush()
        except Exception as flush_error:  # the error in the block is the one to report
            log.error("KD flush after %s failed: %s", et.__name__, flush_error)
        finally:
            self.close()

    def feed(self, frame: LogMessage) -> list[CycleResult]:
        """Take one log frame; returns the cycles it let run (sweeps whose poses are in).

        A frame the node cannot use (:func:`wm.screen.check_frame`: a time that is no
        integer, wrong shapes or dtypes, non-finite values, a rotation that is none, negative
        box sizes, bad intrinsics; :meth:`_screen`: out of time order; :meth:`_hold`: far in
        the future or past) is logged and counted in ``stats.skipped`` and changes nothing: one bad
        message never stops or corrupts a run. A run of frames far in the future or the past
        is a jump of the log's clock: a new segment starts (module docstring). Anything but a
        frame (None, a dict, an array) raises :class:`FrameTypeError`, the node untouched."""
        if not isinstance(frame, FRAME_TYPES):
            raise FrameTypeError(
                f"WorldModelNode.feed takes one log frame "
                f"({', '.join(t.__name__ for t in FRAME_TYPES)}), got {type(frame).__name__}"
            )
        self.stats.frames[type(frame).__name__] += 1
        why = check_frame(frame)  # its content, before its time is trusted for anything
        if why is None and isinstance(frame, LadarScan):
            frame, why = self._finite_points(frame)
        if why is not None:
            self._skipped(frame, why)
            return []
        if self._beyond_jump(frame):
            return self._hold(frame)
        self._skip_held()
        return self._take(frame)

    def _take(self, frame: LogMessage) -> list[CycleResult]:
        """A frame in time: screened, then taken (:meth:`feed`)."""
        why = self._screen(frame)
        if why is not None:
            self._skipped(frame, why)
            return []
        if isinstance(frame, TransformFrame):
            self._transform(frame)
        elif isinstance(frame, GroundTruthPose):
            self.truth.add(frame.t_ns, frame.T_parent_child)
        elif isinstance(frame, OdometryFrame):
            self.last_wheel_t_ns = max(self.last_wheel_t_ns or frame.t_ns, frame.t_ns)
            if self._uses_odometry():
                self._wheel_to_odometry(frame)
        elif isinstance(frame, CameraFrame):
            self.camera = frame
        elif isinstance(frame, ObjectBoxes):
            self.truth_boxes = self._boxes_in_world(frame)
        elif isinstance(frame, LadarScan):
            frame = self._in_ladar_frame(frame)
            self.last_sweep_t_ns = frame.t_ns
            self.pending.append(frame)
        self._learn_gap(int(frame.t_ns))
        self.last_t_ns = frame.t_ns if self.last_t_ns is None else max(self.last_t_ns, frame.t_ns)
        if self._log_start_ns is None:
            self._log_start_ns = int(frame.t_ns)
        out = []
        while self.pending and self._ready(self.pending[0]):
            out += self._start(self.pending.popleft())
        return out

    def _wheel_to_odometry(self, frame: OdometryFrame) -> None:
        """Hand a screened wheel-odometry frame to the odometry; one it still refuses (in
        this process) is counted as skipped, the run goes on."""
        if self.odometry is None and self.T_world_body0 is None:
            self.T_world_body0 = initial_pose(frame)
        try:
            self._odometry().add_wheel_odometry(frame)
        except OdometryError as e:  # the odometry process tells its own with the next sweep
            self._skipped(frame, f"bad odometry pose: {e}")

    def jump_bound_ns(self) -> int:
        """How far (ns) a frame may be stamped from the log's latest one and be taken: the
        median gap between the log's frames times ``time_jump_gaps``, within
        [``min_time_jump_ns``, ``max_time_jump_ns``] (the upper bound alone until
        ``_GAPS_NEEDED`` gaps are known). A bound in the log's own rhythm: a stamp one
        bad message moves a minute ahead would otherwise pass, and every frame of that minute
        after it would be out of order and lost."""
        if self._jump_bound_ns is None:
            return self.config.max_time_jump_ns
        return self._jump_bound_ns

    def _learn_gap(self, t_ns: int) -> None:
        """Keep the gap from the log's latest frame to a frame taken after it; the bound
        (:meth:`jump_bound_ns`) follows every ``_GAPS_NEEDED`` gaps."""
        if self.last_t_ns is None or t_ns <= self.last_t_ns:
            return
        self._gaps.append(t_ns - self.last_t_ns)
        self._n_gaps += 1
        if self._n_gaps % _GAPS_NEEDED == 0:
            c = self.config
            typical = float(np.median(self._gaps)) * c.time_jump_gaps
            self._jump_bound_ns = int(min(c.max_time_jump_ns, max(c.min_time_jump_ns, typical)))

    def _beyond_jump(self, frame: LogMessage) -> bool:
        """The frame is stamped more than :meth:`jump_bound_ns` after the log's latest one,
        or more than that before it (a clock that jumped back)."""
        last = self.last_t_ns
        return last is not None and abs(int(frame.t_ns) - last) > self.jump_bound_ns()

    def _hold(self, frame: LogMessage) -> list[CycleResult]:
        """Hold a frame beyond a time jump; once ``segment_confirm_frames`` held frames agree
        (each within the bound of the one before), start a new segment with them. A frame
        that does not agree with those held replaces them (they are skipped)."""
        bound = self.jump_bound_ns()
        if self.held and abs(int(frame.t_ns) - int(self.held[-1].t_ns)) > bound:
            self._skip_held()
        self.held.append(frame)
        if len(self.held) < self.config.segment_confirm_frames:
            return []
        return self._new_segment()

    def _skip_held(self) -> None:
        """The held frames were outliers (corrupted stamps): skip and count each."""
        for f in self.held:
            self._skipped(f, self._jump_reason(int(f.t_ns)))
        self.held = []

    def _jump_reason(self, t_ns: int) -> str:
        gap_s = (t_ns - (self.last_t_ns or 0)) * 1e-9
        way = "after" if gap_s >= 0 else "before"
        return (
            f"time jump: {abs(gap_s):.3g} s {way} the log's latest frame "
            f"(limit {self.jump_bound_ns() * 1e-9:g} s)"
        )

    def _skipped(self, frame: LogMessage, why: str) -> None:
        self._count_skip(f"{type(frame).__name__} at t_ns={frame.t_ns}", why)

    def _count_skip(self, what: str, why: str) -> None:
        """Count a skip under its reason (``why`` up to its first colon) and log it."""
        self.stats.skipped[why.split(":")[0]] += 1
        log.warning("skipped %s: %s", what, why)

    def _new_segment(self) -> list[CycleResult]:
        """A real gap in the log: end the segment before it (its sweeps run, the KD file is
        flushed), drop what integrates across time (module docstring) and take the held
        frames as the start of the next segment."""
        held, self.held = self.held, []
        last = self.last_t_ns
        out = self._drain()
        self.flush()
        self._restart_continuity()
        self.stats.events["time_jump_new_segment"] += 1
        if last is not None and int(held[0].t_ns) < last:
            # the entities go on, but their relations cannot end on the new clock before
            # they began on the old one
            self.kd.restart_relations(last, int(held[0].t_ns))
        jump_s = (int(held[0].t_ns) - (last or 0)) * 1e-9
        note = (
            f"new segment at t_ns={held[0].t_ns}: the log jumped {abs(jump_s):.4g} s "
            f"{'forward' if jump_s >= 0 else 'back'} from t_ns={last}; "
            f"odometry restarted from the last pose"
        )
        self.stats.notes.append(note)
        log.warning("%s", note)
        self._restart_clock()
        for f in held:
            out += self._take(f)
        return out

    def _restart_clock(self) -> None:
        """Forget the old segment's times, which the held frames set anew: after a jump
        back they are all earlier, and would otherwise be taken for stragglers (skipped as
        out of order), never flush the KD and never be due for the levels' slow work. The
        jump is the recording's, not the file falling behind: the flush lag starts again."""
        self.last_t_ns = None
        self._log_start_ns = None
        self.last_sweep_t_ns = None
        self.last_wheel_t_ns = None
        self._flushed_ns = None
        self._tiles_ns = None
        self.level_due_ns = dict.fromkeys(self.level_due_ns, -(2**62))

    def _restart_continuity(self) -> None:
        """Forget what integrates across time: the odometry (restarted lazily, from the last
        pose of the track), the pose track and last cycle's range-image prediction."""
        if self._uses_odometry():
            if self.track.t_ns:
                self.T_world_body0 = self.track.poses[-1].copy()
            self.close()
            self.odometry = None
            self.track = PoseTrack()
        self.prediction = None
        self.attention_world_xyz = None

    def _screen(self, frame: LogMessage) -> str | None:
        """Why ``frame`` must be skipped for its time order ("reason: detail"), or None to
        take it; its content was checked on the way in (:func:`wm.screen.check_frame`)."""
        t = int(frame.t_ns)
        if isinstance(frame, OdometryFrame):
            if self.last_wheel_t_ns is not None and t <= self.last_wheel_t_ns:
                return f"odometry out of order: t_ns {t} <= {self.last_wheel_t_ns}"
        elif isinstance(frame, LadarScan):
            if self.last_sweep_t_ns is not None and t <= self.last_sweep_t_ns:
                return f"sweep out of order: t_ns {t} <= {self.last_sweep_t_ns}"
        return None

    def _finite_points(self, scan: LadarScan) -> tuple[LadarScan, str | None]:
        """The sweep without its non-finite or absurdly far points (counted in
        ``stats.dropped_nonfinite_points``; wm.screen says why they are dropped, not the
        sweep), or a reason to skip it when none is left."""
        kept, dropped = finite_points(scan)
        if dropped and kept.n_points == 0:
            return scan, f"bad sweep: none of its {dropped} points is finite and in range"
        self.stats.dropped_nonfinite_points += dropped
        return kept, None

    def finish(self) -> list[CycleResult]:
        """End of log: run the sweeps still waiting, flush the KD (:meth:`flush`) and stop
        the odometry process. Frames still held beyond a time jump are skipped. Calling it
        again does nothing more."""
        try:
            self._skip_held()
            out = self._drain()
            self.flush()
        finally:
            self.close()
        return out

    def flush(self) -> None:
        """Long-term memory and pending map tiles to the KD file now, in one transaction (a
        throwaway or read-only KD keeps them in RAM)."""
        again = (self.stats.sweeps, self.last_t_ns) == self._flushed_at  # finish() twice
        self._note_lag()
        self.kd.flush(tiles=True)
        self.stats.kd_flushes += 0 if again else 1
        self._flushed_at = (self.stats.sweeps, self.last_t_ns)
        if self.last_t_ns is not None:  # everything taken so far is in the file now
            self._flushed_ns = self.last_t_ns
        if not again:  # the end of the log (or of a segment): the snapshot is due
            self.publish_snapshot(tiles=True)

    def _note_lag(self) -> None:
        """Just before a flush, the KD file is furthest behind the log (``stats``)."""
        since = self._flushed_ns if self._flushed_ns is not None else self._log_start_ns
        if self.last_t_ns is not None and since is not None:
            lag = int(self.last_t_ns) - int(since)
            self.stats.kd_flush_max_lag_ns = max(self.stats.kd_flush_max_lag_ns, lag)

    def _drain(self) -> list[CycleResult]:
        """Run every sweep still waiting for its poses or at the odometry process."""
        out = []
        while self.pending:
            out += self._start(self.pending.popleft())
        while self.inflight:
            out += self._cycles(*self.inflight.popleft())
        return out

    def whatis(self) -> WhatIs:
        """What Is over this node's KD and maps, knowing the self entity and the LADAR mount."""
        return WhatIs(self.kd, self.stack, self.self_id, self.T_body_ladar)

    def set_plan(self, xy_world: np.ndarray | None) -> None:
        """Tell the node the controller's current plan: its path (S, 2) in world metres, or
        None when there is none. Until the next call, each level's attention step ranks
        entities near it higher (4.3: relevance to the current plan; ``VJConfig.w_relevance``
        within ``relevance_radius_m``). ``wm.bg.Planner(on_select=node.set_plan)`` keeps it
        current. Another thread may call it while a cycle runs: the path is checked first and
        then replaces ``plan_xy`` whole, and a cycle reads ``plan_xy`` once, so each cycle ranks
        every level against one plan."""
        if xy_world is None:
            self.plan_xy = None
            return
        xy = np.asarray(xy_world, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] < 2 or len(xy) == 0:
            raise NodeError(f"set_plan: the plan must be an (S, 2) path in world m, got {xy.shape}")
        if not np.all(np.isfinite(xy[:, :2])):
            k = int(np.flatnonzero(~np.isfinite(xy[:, :2]).all(axis=1))[0])
            raise NodeError(f"set_plan: plan point {k} is not finite: {xy[k, :2].tolist()}")
        self.plan_xy = xy[:, :2].copy()

    def close(self) -> None:
        """Stop the odometry process, if one runs (the node can still answer queries)."""
        if isinstance(self.odometry, OdometryWorker):
            self.odometry.close()

    def _start(self, scan: LadarScan) -> list[CycleResult]:
        """A sweep whose poses are in: run its cycle now, or, with the odometry process,
        submit it and run the oldest sweep's cycle once ``odometry_ahead`` are in hand there
        (the process registers them meanwhile)."""
        if not (self._uses_odometry() and self.config.odometry_process):
            return self._cycles(scan, self.camera)
        self._odometry(scan).submit(scan)
        self.inflight.append((scan, self.camera))
        ahead = self.config.odometry_ahead
        return self._cycles(*self.inflight.popleft()) if len(self.inflight) > ahead else []

    def _cycles(self, scan: LadarScan, camera: CameraFrame | None) -> list[CycleResult]:
        """The sweep's cycle as a list: empty when the sweep got no pose (skipped)."""
        result = self.cycle(scan, camera)
        return [] if result is None else [result]

    def _ready(self, scan: LadarScan) -> bool:
        """The log has passed the sweep's last point and, when it carries wheel odometry,
        that has too (or stayed silent ``wheel_wait_ns`` past it): the odometry's prediction
        then interpolates the wheels over the whole sweep whatever other topics are
        interleaved with them."""
        end = scan.t_ns + (int(scan.t_offset_ns.max()) if scan.n_points else 0)
        if self.last_t_ns is None or self.last_t_ns <= end:
            return False
        wheel = self.last_wheel_t_ns
        return wheel is None or wheel >= end or self.last_t_ns > end + self.config.wheel_wait_ns

    def _transform(self, frame: TransformFrame) -> None:
        if frame.parent_frame_id != BODY:
            return
        self.mounts[frame.child_frame_id] = frame.T_parent_child
        if frame.child_frame_id.startswith(CAMERA):
            self.T_body_camera = frame.T_parent_child

    def _in_ladar_frame(self, scan: LadarScan) -> LadarScan:
        """``scan`` in the LADAR's own frame, whose origin SP's egosphere looks from.

        The first sweep fixes the mount ``T_body_ladar``: the log's transform from
        ``base_link`` to the sweep's frame; for a sweep given in ``base_link``, the log's
        ``ladar`` mount, into which its points are moved (seen from the body's origin, on
        the ground under a car, every elevation would be wrong); with neither, the body
        itself (noted in ``stats.notes``)."""
        if self.T_body_ladar is None:
            in_body = scan.frame_id == BODY
            T = self.mounts.get(LADAR) if in_body else mount_of(scan.frame_id, self.mounts)
            self._body_to_ladar = in_body and T is not None
            if T is None:
                T = np.eye(4)
                self.stats.notes.append(
                    f"no {BODY}->{LADAR if in_body else scan.frame_id} transform in the log:"
                    f" LADAR taken at the body"
                )
            self.T_body_ladar = np.asarray(T, dtype=np.float64)
        if scan.frame_id != BODY or not self._body_to_ladar:
            return scan
        R, t = self.T_body_ladar[:3, :3], self.T_body_ladar[:3, 3]
        xyz = ((scan.points_xyz.astype(np.float64) - t) @ R).astype(np.float32)
        return dataclasses.replace(scan, points_xyz=xyz, frame_id=LADAR)

    def _boxes_in_world(self, boxes: ObjectBoxes) -> ObjectBoxes | None:
        """Ground-truth boxes in the world frame (body-frame boxes moved with the true pose)."""
        if boxes.frame_id == "world":
            return boxes
        if boxes.frame_id != BODY or not self.truth.t_ns:
            return None
        try:
            T = self.truth.at(boxes.t_ns)
        except PoseError:
            return None
        return truth_boxes_to_world(boxes, T)

    def _uses_odometry(self) -> bool:
        return self.config.pose_source == PoseSource.ODOMETRY

    def _odometry(self, scan: LadarScan | None = None) -> Any:
        if self.odometry is None and self.T_world_body0 is None and scan is not None:
            # no wheel odometry to give the attitude: level the world on the first sweep's ground
            mount = self.T_body_ladar if self.T_body_ladar is not None else np.eye(4)
            self.T_world_body0 = level_from_ground(scan.points_xyz, mount)
        if self.odometry is None:
            from sp.odometry import LadarOdometry

            T0 = self.T_world_body0
            odo = self.engine_config.odometry
            if self.config.odometry_process:
                self.odometry = OdometryWorker(self.T_body_ladar, T0, odo)
            else:
                self.odometry = LadarOdometry(
                    odo, T_body_sensor=self.T_body_ladar, T_world_body0=T0
                )
        return self.odometry

    # --- the cycle -------------------------------------------------------------------------

    def cycle(self, scan: LadarScan, camera: CameraFrame | None = None) -> CycleResult | None:
        """One node cycle on one sweep (module docstring, steps 1-6); ``camera`` is the latest
        image when the sweep's poses came in. None when the odometry could not place the
        sweep (counted in ``stats.skipped["odometry failed"]``): nothing else is done."""
        clock = _StageClock(self.stats)
        scan = self._in_ladar_frame(scan)
        status = self._pose(scan)
        if status is None:
            return None
        self.kd.begin_cycle(scan.t_ns)
        span = int(scan.t_offset_ns.max()) if scan.n_points else 0
        t_mid = scan.t_ns + span // 2
        T_world_body = self.track.at(t_mid)
        T_world_ladar = T_world_body @ self.T_body_ladar
        pts = deskew_to_world(
            scan.points_xyz, scan.t_offset_ns, scan.t_ns, self.track, self.T_body_ladar,
            self.config.deskew_bins,
        )  # fmt: skip
        self._self_state(t_mid, T_world_body)
        clock.lap("pose")

        if self.prediction is not None:  # last cycle's expectation of this sweep
            self._compare_prediction(pts, T_world_ladar)
        self.stack.move_to_pose(T_world_body)
        if len(pts):
            self.stack.fuse(
                pts,
                t_ns=scan.t_ns,
                sensor_xyz=T_world_ladar[:3, 3],
                ray_origin_xyz=T_world_ladar[:3, 3],  # free space along the beams
            )
        clock.lap("maps")

        sp_result = self._sensory_processing(scan, T_world_ladar, t_mid, camera, pts)
        clock.lap("sp")
        self._update_entities(sp_result)
        clock.lap("entities")

        self._levels(scan.t_ns)
        clock.lap("levels")

        self._predict(scan, T_world_body, span)
        if self.stats.sweeps % self.config.kd_advance_every == 0:
            forgotten = self.kd.advance(scan.t_ns)
            if self.sp is not None:
                self.sp.frames_forgotten(forgotten)
        clock.lap("predict")
        self._flush(scan.t_ns)
        clock.lap("flush")
        self.stats.sweeps += 1
        self.stats.odometry_status[status] += 1
        result = CycleResult(scan.t_ns, T_world_body, len(pts), t_mid, sp_result, status)
        for listener in self.cycle_listeners:
            listener(result)
        return result

    def _flush(self, t_ns: int) -> None:
        """Long-term memory to the KD file every ``kd_flush_every_ns`` of log time, in one
        transaction: what was written survives a killed process, and another reader of the
        file sees the run up to then. Map tiles go every ``kd_tile_flush_every_ns`` (their
        compression is most of a flush's cost)."""
        cfg = self.config
        if self._flushed_ns is not None and t_ns - self._flushed_ns < cfg.kd_flush_every_ns:
            return
        tiles = self._tiles_ns is None or t_ns - self._tiles_ns >= cfg.kd_tile_flush_every_ns
        self._note_lag()
        self.kd.flush(tiles=tiles)
        self.stats.kd_flushes += 1
        self._flushed_ns = t_ns
        self._tiles_ns = t_ns if tiles else self._tiles_ns
        last = self._snapshot_ns
        every_ns = round(cfg.snapshot_every_s * 1e9)
        if last is None or t_ns - last >= every_ns or t_ns < last:  # < : the clock jumped back
            self.publish_snapshot(tiles=tiles, t_ns=t_ns)

    @property
    def flushed_t_ns(self) -> int | None:
        """Log time (ns) up to which the KD file holds the run: every cycle up to this time
        was flushed (None before the first flush, and again after a jump of the clock)."""
        return self._flushed_ns

    def publish_snapshot(self, tiles: bool = True, t_ns: int | None = None) -> None:
        """Publish the read-only copy of the KD file (``NodeConfig.snapshot_path``; nothing
        when None) now, stamped ``t_ns`` (log time; default the newest frame's) for the next
        one's timing. A copy that fails is logged and counted (``stats.snapshot_failures``),
        never stops the run: the KD file is what the run writes, the copy only a window on it."""
        path = self.config.snapshot_path
        if path is None:
            return
        t0 = time.perf_counter()
        try:
            self.kd.publish_snapshot(path, tiles=tiles)
        except (OSError, kd_store.KDError) as e:
            self.stats.snapshot_failures += 1
            log.warning("KD snapshot %s not published: %s", path, e)
            return
        self.stats.snapshot_ms.append(1e3 * (time.perf_counter() - t0))
        self._snapshot_ns = t_ns if t_ns is not None else self.last_t_ns

    def _pose(self, scan: LadarScan) -> str | None:
        """Step 1: extend the pose track over this sweep; returns the odometry status, or
        None when the odometry failed on the sweep (counted as skipped; it restarts from its
        last accepted pose)."""
        if self.config.pose_source == PoseSource.TRUTH:
            if not self.truth.t_ns:
                raise NodeError(
                    f"pose source 'truth' but no ground-truth pose before the sweep at "
                    f"t_ns={scan.t_ns}; use the odometry pose source for this log"
                )
            self.track = self.truth
            return "truth"
        odo = self._odometry(scan)
        if isinstance(odo, OdometryWorker):
            reply = odo.result()
            self.stats.stage_cpu_s["odometry"] += reply.cpu_s
        else:
            est, why = odo.update_or_skip(scan)
            reply = OdometryReply(est, 0.0, [why] if why else [])
        for why in reply.skipped:
            self._count_skip("odometry request", why)
        est = reply.estimate
        if est is None:
            return None
        self.track.add(est.t_ns, est.T_world_body)
        return str(est.status)

    def _self_state(self, t_ns: int, T_world_body: np.ndarray) -> None:
        """Step 2: the vehicle's own state (world frame) into the KD."""
        v = self.track.velocity(t_ns)
        q = matrix_to_quat(T_world_body[:3, :3])
        state = State(t_ns, "world", T_world_body[:3, 3], q, v)
        try:
            self.kd.observe(self.self_id, state)
        except kd_store.KDError:  # a repeated time (same sweep middle): keep the first
            pass

    def _sensory_processing(
        self,
        scan: LadarScan,
        T_world_ladar: np.ndarray,
        t_pose_ns: int,
        camera: CameraFrame | None,
        points_world: np.ndarray | None = None,
    ) -> SPResult | None:
        """Step 4: SP levels 2..5 and their labels into the maps. ``T_world_ladar`` is the
        sensor pose at ``t_pose_ns`` (the sweep's middle); ``points_world`` (N, 3) m the sweep
        as the maps fused it (deskewed once, on the pose track), so SP's points and labels
        lie where the maps' points do."""
        if self.sp is None:
            return None
        cam, T_world_camera = None, None
        if camera is not None and self.T_body_camera is not None:
            try:
                T_world_camera = self.track.at(camera.t_ns) @ self.T_body_camera
                cam = camera
            except PoseError:
                pass
        result = self.sp.process(
            scan,
            T_world_ladar,
            camera=cam,
            T_world_camera=T_world_camera,
            attention_world_xyz=self.attention_world_xyz,
            pose_t_ns=t_pose_ns,
            points_world=points_world,
            ground_prior=self._ground_prior(),
        )
        if len(result.points_world):
            self.stack.fuse_labels(
                result.points_world, result.point_entity_ids, result.point_class_ids
            )
        for name, s in getattr(result, "timings_s", {}).items():
            self.stats.stage_s[f"sp.{name}"] += float(s)
        return result

    def _ground_prior(self) -> GroundPrior | None:
        """The ground SP should expect: the ground heights of the map level
        ``ground_prior_level``, fused from earlier sweeps and this one (a view of the level's
        storage, read during SP's call only)."""
        name = self.config.ground_prior_level
        if name is None:
            return None
        lvl = self.stack.level(name)
        ix0, iy0 = (int(v) for v in lvl.origin_cell)
        return GroundPrior(
            lvl.storage("elevation"), (ix0, iy0), lvl.resolution_m,
            lvl.storage("elevation_min"), lvl.storage("elevation_max"),
        )  # fmt: skip

    def _update_entities(self, sp_result: SPResult | None) -> None:
        """Step 4, the world model's part: SP's observations into the KD (entity and event
        frames, states, relations), in the order SP made them (:mod:`wm.entities`). A write
        the KD refuses is counted and logged, and the rest of the sweep's observations are
        skipped (``stats.skipped["entity update refused"]``), as SP skipped the rest of a
        sweep whose write the KD refused when SP wrote the KD itself. SP is told how many
        were written, so what it assumes of its frames in the KD stays true."""
        if sp_result is None or self.sp is None:
            return
        n_written = None
        try:
            self.entities.apply(sp_result.observations)
        except kd_store.KDError as e:
            n_written = self.entities.n_applied
            self._count_skip(
                f"SP observations at t_ns={sp_result.t_ns}", f"entity update refused: {e}"
            )
        self.sp.observations_written(sp_result, n_written)

    def _levels(self, t_ns: int) -> None:
        """Step 5: each level's terrain and cost layer, at the level's own period."""
        periods = self.config.level_periods_s
        # one plan for every level of the cycle: set_plan may replace it from another thread
        # meanwhile (wm serve's POST /v1/plan, which does not wait for the cycle)
        plan_xy = self.plan_xy
        for lvl in self.stack.levels:
            period_ns = round(periods.get(lvl.name, 1.0) * 1e9)
            if t_ns < self.level_due_ns[lvl.name]:
                continue
            self.level_due_ns[lvl.name] = t_ns + period_ns
            update_terrain(lvl, self.stack.config.terrain)
            vj.write_cost_layer(lvl, self.kd, self.config.vj)
            self._attention(lvl, plan_xy)

    def _attention(self, lvl, plan_xy: np.ndarray | None) -> None:
        """The level's entities of attention, proximity judged on the level's own scale,
        relevance against the plan ``plan_xy`` (the current one, :meth:`set_plan`)."""
        if self.stack.T_world_body is None:
            return
        cfg = dataclasses.replace(self.config.vj, proximity_scale_m=25.0 * lvl.resolution_m)
        xy = self.stack.T_world_body[:2, 3]
        att = vj.attention(self.kd, xy, cfg, plan_xy=plan_xy, skip=self.self_id)
        try:
            self.kd.set_attention(lvl.name, att.ids.tolist())
        except kd_store.KDError:
            pass  # the KD keeps no attention list for this level

    def _predict(self, scan: LadarScan, T_world_body: np.ndarray, span_ns: int) -> None:
        """Step 6: expected entity states; every few sweeps a predicted range image."""
        cfg = self.config.prediction
        predict.expect_entities(
            self.kd, cfg.expectation_steps_s, cfg.expect_min_confidence, skip=self.self_id
        )
        every = cfg.range_image_every
        self.prediction = None
        if every and self.stats.sweeps % every == 0 and len(self.track) >= 2:
            period_ns = max(span_ns, 50_000_000)
            t_next = scan.t_ns + period_ns + span_ns // 2
            try:
                T_next = self.track.at(t_next)
            except PoseError:
                return
            has = self._has("subsystem")
            level = self.stack.level("subsystem") if has else self.stack.levels[0]
            self.prediction = predict.predict_range_image(
                level, self.kd, T_next @ self.T_body_ladar, t_next, cfg, scan, skip=self.self_id
            )

    def _has(self, name: str) -> bool:
        return any(lvl.name == name for lvl in self.stack.levels)

    def _compare_prediction(self, pts_world: np.ndarray, T_world_ladar: np.ndarray) -> None:
        pred = self.prediction
        assert pred is not None
        cmp = predict.compare(pred, pts_world, T_world_ladar, self.config.prediction)
        self.prediction = None
        if cmp is None:
            return
        self.stats.range_image_error_m.append(cmp.median_abs_error_m)
        self.stats.surprise_fraction.append(cmp.surprise_fraction)
        self.attention_world_xyz = cmp.surprise_world_xyz
        self.surprises.update(self.kd, cmp, pred.t_ns)
