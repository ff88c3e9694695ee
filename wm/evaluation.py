"""Scores of one KD against one log's ground truth: what a user of the KD sees, measured with
established libraries (py-motmetrics for CLEAR-MOT and identity metrics, TrackEval for HOTA,
evo for trajectories). The protocol is written down in ``docs/evaluation.md``; this module is
its one implementation.

Frames: ``world`` is the truth's world (GroundTruthPose, truth boxes); ``odom`` is the world of
the KD (the frame of the ``self`` entity's states, the odometry's world). Tracking is compared
in the body frame: hypotheses in the ESTIMATED body frame (KD self pose), truth boxes in the
TRUE body frame (log pose), so tracking figures do not include odometry drift; the trajectory
figures score the drift on its own.

Times are int64 ns; lengths m; speeds m/s; poses 4x4 float64 ``T_a_b`` (``p_a = T_a_b @ p_b``).
"""

from __future__ import annotations

import contextlib
import io
import math
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from core.errors import EngineError
from core.geometry import (
    BODY,
    footprint_distance,
    mount_of,
    pose_from_xyz_quat,
    se3_inverse,
    transform_points,
)
from wm.poses import PoseTrack, deskew_to_world
from wm.truth import CLASS_ALIASES

#: SP object level (kd_store.Level.OBJECT); the level whose entities are scored.
OBJECT_LEVEL = 4
#: Statuses whose entities count as hypotheses, from their confirmation on. The tracker moves
#: only confirmed tracks to ``gone`` (sp/tracking.py: too many misses), so a gone entity was
#: shown to the user as confirmed until it was lost.
SCORED_STATUSES = ("confirmed", "gone")


class EvaluationError(EngineError, ValueError):
    """A KD or log that cannot be scored (names the file and what is missing)."""


@dataclass(frozen=True)
class EvalConfig:
    """The protocol's constants (docs/evaluation.md)."""

    range_m: float = 40.0  # scored range, body xy plane
    dont_care_band_m: float = 1.0  # [range_m, range_m + band) is "don't care"
    match_m: float = 1.0  # largest footprint distance of a match
    state_window_ns: int = 250_000_000  # a hypothesis needs a state in (t - window, t + lead]
    truth_dt_ns: int = 100_000_000  # truth boxes at most this far from t
    min_points: int = 5  # fewer LADAR returns on the object (or in its grown box): "don't care"
    box_grow_m: float = 0.1  # each box grown by this on every side to count returns
    static_speed_mps: float = 0.05  # a true speed below this is static
    deskew_bins: int = 8  # slices of a sweep moved each with its own true pose
    rpe_delta_m: float = 10.0  # RPE segment length
    statuses: tuple[str, ...] = SCORED_STATUSES
    # recall is also given per band of box range: [0, 20), [20, 30), [30, range_m] m
    range_bands_m: tuple[float, ...] = (20.0, 30.0)
    # ... and for the log's first seconds (from its first scored time), where every object in
    # range is new at once and waits for its track's confirmation, and for the rest
    startup_s: float = 1.0


# --- ground truth from a log ---------------------------------------------------------------


@dataclass
class Sweep:
    """One LADAR sweep: ``points_xyz`` (N, 3) float32 m in the LADAR frame, ``t_offset_ns``
    (N,) int64 after ``t_ns``."""

    t_ns: int
    points_xyz: np.ndarray
    t_offset_ns: np.ndarray

    @property
    def mid_ns(self) -> int:
        span = int(self.t_offset_ns.max()) if len(self.t_offset_ns) else 0
        return self.t_ns + span // 2

    @property
    def end_ns(self) -> int:
        return self.t_ns + (int(self.t_offset_ns.max()) if len(self.t_offset_ns) else 0)


@dataclass
class Seen:
    """How one sweep saw the truth: its middle time ``mid_ns``, and for the boxes of the set
    nearest that time (ids (M,) int64) the LADAR returns in each grown box (M,) int64; ``ids``
    None when the truth poses do not cover the sweep (visibility unknown)."""

    mid_ns: int
    ids: np.ndarray | None
    points: np.ndarray

    def count(self, box_ids: np.ndarray) -> np.ndarray:
        """Returns per box id (K,) int64: 0 for a box the sweep did not count, -1 for all
        when visibility is unknown."""
        if self.ids is None:
            return np.full(len(box_ids), -1, dtype=np.int64)
        lookup = dict(zip(self.ids.tolist(), self.points.tolist(), strict=True))
        return np.array([lookup.get(int(i), 0) for i in box_ids], dtype=np.int64)


@dataclass
class Truth:
    """A log's ground truth: true body poses, truth boxes in the truth world (time order),
    what each LADAR sweep saw of them (:class:`Seen`, in time order) and the static mount
    ``T_body_ladar`` (4x4) of the sweeps' frame (the identity for sweeps in ``base_link``).
    The sweeps themselves are not kept: a long log's points would not fit in memory."""

    poses: PoseTrack
    boxes: list[Any]  # logs.types.ObjectBoxes, frame "world", classes after CLASS_ALIASES
    seen: list[Seen]
    T_body_ladar: np.ndarray = field(default_factory=lambda: np.eye(4))

    @property
    def box_t_ns(self) -> np.ndarray:
        return np.array([b.t_ns for b in self.boxes], dtype=np.int64)

    @classmethod
    def from_sweeps(
        cls,
        poses: PoseTrack,
        boxes: list[Any],
        sweeps: list[Sweep],
        T_body_ladar: np.ndarray | None = None,
        config: EvalConfig = EvalConfig(),
    ) -> Truth:
        """The truth of world-frame ``boxes`` and ``sweeps`` counted against them."""
        truth = cls(poses, list(boxes), [], np.eye(4) if T_body_ladar is None else T_body_ladar)
        truth.seen = [see(truth, sw, config) for sw in sweeps]
        return truth


def see(truth: Truth, sweep: Sweep, config: EvalConfig) -> Seen:
    """What ``sweep`` saw of the truth boxes nearest its middle (moved to it), for each box
    within reach of the true body: the sweep's returns on the object itself where the log says
    (``ObjectBoxes.n_returns`` of the box set stamped at the sweep's start: ground truth per
    return); otherwise its returns, each moved to the true world with the true pose at its own
    time, inside the box grown by ``box_grow_m``."""
    t = sweep.mid_ns
    got = truth_at(truth, t, config) if truth.boxes else None
    if got is None or not truth.poses.covers(t):
        return Seen(t, None, np.zeros(0, dtype=np.int64))
    boxes, centers = got
    labelled = _returns_of_sweep(truth, sweep.t_ns)
    T_body_world = se3_inverse(truth.poses.at(t))
    c_body = transform_points(T_body_world, centers)
    yaw_body = boxes.yaws + math.atan2(T_body_world[1, 0], T_body_world[0, 0])
    reach = config.range_m + config.dont_care_band_m
    body_origin = np.zeros((1, 2))
    range_m = footprint_distance(body_origin, c_body[:, :2], boxes.sizes[:, :2], yaw_body)[:, 0]
    near = np.flatnonzero(range_m < reach)
    if labelled is not None:
        lookup = dict(zip(labelled.ids.tolist(), labelled.n_returns.tolist(), strict=True))
        counts = np.array([lookup.get(int(i), 0) for i in boxes.ids[near]], dtype=np.int64)
        return Seen(t, boxes.ids[near].astype(np.int64), counts)
    try:
        p_world = deskew_to_world(
            sweep.points_xyz, sweep.t_offset_ns, sweep.t_ns, truth.poses, truth.T_body_ladar,
            config.deskew_bins,
        )  # fmt: skip
    except ValueError:  # the truth poses do not cover the sweep: visibility unknown
        return Seen(t, None, np.zeros(0, dtype=np.int64))
    counts = points_in_boxes(
        p_world, centers[near], boxes.sizes[near], boxes.yaws[near], config.box_grow_m
    )
    return Seen(t, boxes.ids[near].astype(np.int64), counts)


def _returns_of_sweep(truth: Truth, sweep_t_ns: int) -> Any | None:
    """The box set stamped at the sweep's start when it counts the sweep's returns per object
    (the simulator's truth), else None."""
    bt = truth.box_t_ns
    k = int(np.searchsorted(bt, sweep_t_ns))
    if k < len(bt) and int(bt[k]) == sweep_t_ns and truth.boxes[k].n_returns is not None:
        return truth.boxes[k]
    return None


def unbounded_track() -> PoseTrack:
    """A PoseTrack that keeps every pose (a log's whole truth), no extrapolation past 0.2 s."""
    return PoseTrack(horizon=1 << 40)


def load_truth(
    log_path: str | Path, config: EvalConfig = EvalConfig(), *, skip_corrupt: bool = False
) -> Truth:
    """Ground truth of a log (GroundTruthPose, ObjectBoxes, LadarScan, static base_link->ladar
    TransformFrame). Body-frame boxes are moved to the world with the true pose at their time.
    Each sweep is counted against the boxes (:func:`see`) once the poses cover it and the box
    set nearest its middle is in, and then let go. Raises EvaluationError when the log has no
    true poses or no truth boxes, or when the log cannot be read (ground truth unavailable;
    ``skip_corrupt`` reads on past damaged records)."""
    from logs import LogError, open_log

    try:
        return _load_truth(log_path, config, open_log(log_path, skip_corrupt=skip_corrupt))
    except LogError as e:
        raise EvaluationError(f"ground truth unavailable: {e}") from e


def _load_truth(log_path: str | Path, config: EvalConfig, source: Any) -> Truth:
    """:func:`load_truth` from an open log source."""
    from logs.types import GroundTruthPose, LadarScan, ObjectBoxes, TransformFrame

    truth = Truth(unbounded_track(), [], [])
    waiting_boxes: list[ObjectBoxes] = []  # body-frame sets whose pose is not in yet
    waiting: deque[Sweep] = deque()
    last_box_ns = -(2**62)
    kinds = (GroundTruthPose, ObjectBoxes, LadarScan, TransformFrame)
    mounts: dict[str, np.ndarray] = {}  # child frame -> T_body_child, from /tf_static
    mount_fixed = False
    for f in source.frames(kinds=kinds):
        if isinstance(f, GroundTruthPose):
            truth.poses.add(f.t_ns, f.T_parent_child)
        elif isinstance(f, ObjectBoxes):
            if f.topic == "/ground_truth/objects":
                waiting_boxes.append(f)
                last_box_ns = max(last_box_ns, int(f.t_ns))
        elif isinstance(f, LadarScan):
            if not mount_fixed:  # the first sweep's frame and the mounts then known
                mount_fixed = True
                T = mount_of(f.frame_id, mounts)
                truth.T_body_ladar = np.eye(4) if T is None else T
            waiting.append(Sweep(f.t_ns, f.points_xyz, np.asarray(f.t_offset_ns, np.int64)))
        elif f.static and f.parent_frame_id == BODY:
            mounts[f.child_frame_id] = np.asarray(f.T_parent_child, dtype=np.float64)
        waiting_boxes = _boxes_to_world(truth, waiting_boxes)
        last_pose_ns = truth.poses.t_ns[-1] if len(truth.poses) else -(2**62)
        while (
            waiting
            and waiting[0].end_ns <= last_pose_ns
            and (waiting[0].mid_ns + config.truth_dt_ns <= last_box_ns)
        ):
            truth.seen.append(see(truth, waiting.popleft(), config))
    _boxes_to_world(truth, waiting_boxes, last=True)
    truth.seen += [see(truth, sw, config) for sw in waiting]
    if not len(truth.poses):
        raise EvaluationError(
            f"log {log_path}: ground truth unavailable: no /ground_truth/pose to score against"
        )
    if not truth.boxes:
        raise EvaluationError(
            f"log {log_path}: ground truth unavailable: no /ground_truth/objects boxes"
        )
    return truth


def _boxes_to_world(truth: Truth, sets: list[Any], last: bool = False) -> list[Any]:
    """Moves the box sets the truth can place into ``truth.boxes`` (world frame, CLASS_ALIASES
    applied); returns those still waiting for a true pose (none when ``last``)."""
    from wm.truth import truth_boxes_to_world

    rest = []
    for b in sets:
        if b.frame_id == "world":
            truth.boxes.append(truth_boxes_to_world(b, np.eye(4)))
        elif b.frame_id == "base_link" and truth.poses.covers(b.t_ns):
            truth.boxes.append(truth_boxes_to_world(b, truth.poses.at(b.t_ns)))
        elif b.frame_id == "base_link" and not last:
            rest.append(b)
    return rest


# --- what the KD holds ---------------------------------------------------------------------


@dataclass
class KDRun:
    """What one KD says: self poses ``T_odom_body`` (K, 4, 4) at ``self_t_ns`` (K,), and the
    states of the scored object entities (rows in time order per entity): ``ent_id`` (S,),
    ``t_ns`` (S,), ``xyz`` (S, 3) m in odom, ``vxy`` (S, 2) m/s in odom; ``classes`` maps each
    scored entity id to its predicted class names (a set); ``person_ids`` those predicted
    person."""

    self_t_ns: np.ndarray
    T_odom_body: np.ndarray
    ent_id: np.ndarray
    t_ns: np.ndarray
    xyz: np.ndarray
    vxy: np.ndarray
    classes: dict[int, frozenset[str]]

    @property
    def person_ids(self) -> set[int]:
        return {i for i, c in self.classes.items() if "person" in c and i in set(self.ent_id)}


def predicted_classes(
    generic: list[str] | None, specific: str | None, is_a: dict[str, str] | None = None
) -> frozenset[str]:
    """The classes an entity claims: its most specific generic class (the last of
    ``generic_classes``, which run general to specific) and its ``specific_class``, each with
    the classes it is a kind of (``is_a``: class -> parent, from the KD's class library), so a
    ``freestanding wall`` claims ``wall``. A parent such as ``vegetation`` does not count as
    claiming ``tree``: claims go up the library, never down."""
    out = set()
    for c in ([generic[-1]] if generic else []) + ([specific] if specific else []):
        seen = 0
        while c and seen < 32:  # the library is a tree; the bound guards a cycle
            out.add(CLASS_ALIASES.get(c, c))
            c, seen = (is_a or {}).get(c), seen + 1
    return frozenset(out)


def load_kd(kd: Any, config: EvalConfig = EvalConfig()) -> KDRun:
    """The self poses and scored object states of ``kd`` (a path, opened read-only, or an open
    ``kd_store.KnowledgeDatabase``). Scored: level-4 entities other than ``self`` whose final
    status is in ``config.statuses``, their states from their first ``confirmed`` event on (all
    states when the KD holds no such event). Every state must be in the self state's frame."""
    import kd_store

    if isinstance(kd, str | Path):
        if not Path(kd).exists():
            raise FileNotFoundError(f"KD file {kd} does not exist")
        with kd_store.open(kd, read_only=True) as db:
            return load_kd(db, config)
    run = kd.run_filter()  # the KD's run: a file may hold several, each in its own frame
    selves = kd.sql(f"SELECT id FROM entities WHERE name = 'self' AND {run}").column("id")
    selves = selves.to_pylist()
    if not selves:
        raise EvaluationError("the KD has no 'self' entity: no poses to score at")
    s = kd.sql(
        f"SELECT t_ns, frame, x, y, z, qx, qy, qz, qw FROM entity_states "
        f"WHERE entity_id = {int(selves[0])} ORDER BY t_ns"
    ).to_pydict()
    if not s["t_ns"]:
        raise EvaluationError("the KD's 'self' entity has no states")
    frame = s["frame"][0]
    T = np.stack(
        [
            pose_from_xyz_quat(np.array(p[:3]), np.array(p[3:]))
            for p in zip(*(s[k] for k in ("x", "y", "z", "qx", "qy", "qz", "qw")), strict=True)
        ]
    )
    statuses = ", ".join(f"'{x}'" for x in config.statuses)
    ents = kd.sql(
        f"SELECT id, generic_classes, specific_class FROM entities WHERE level = {OBJECT_LEVEL} "
        f"AND name <> 'self' AND status IN ({statuses}) AND {run}"
    ).to_pydict()
    lib = kd.sql("SELECT name, is_a FROM classes").to_pydict()
    is_a = {n: p for n, p in zip(lib["name"], lib["is_a"], strict=True) if p}
    classes = {
        int(i): predicted_classes(g, sc, is_a)
        for i, g, sc in zip(
            ents["id"], ents["generic_classes"], ents["specific_class"], strict=True
        )
    }
    conf = kd.sql(
        "SELECT r.dst_id AS id, min(ev.t_start_ns) AS t FROM events ev JOIN relations r "
        "ON r.src_id = ev.id AND r.kind = 'involves' WHERE ev.class_name = 'confirmed' "
        "GROUP BY r.dst_id"
    ).to_pydict()
    t_conf = dict(zip(conf["id"], conf["t"], strict=True))
    st = kd.sql(
        f"SELECT s.entity_id, s.t_ns, s.frame, s.x, s.y, s.z, s.vx, s.vy FROM entity_states s "
        f"JOIN entities e ON e.id = s.entity_id WHERE e.level = {OBJECT_LEVEL} "
        f"AND e.name <> 'self' AND e.status IN ({statuses}) AND {kd.run_filter('e')} "
        "ORDER BY s.entity_id, s.t_ns"
    ).to_pydict()
    bad = {f for f in st["frame"] if f != frame}
    if bad:
        raise EvaluationError(f"object states in frames {sorted(bad)}, self states in {frame!r}")
    ent_id = np.asarray(st["entity_id"], dtype=np.int64)
    t_ns = np.asarray(st["t_ns"], dtype=np.int64)
    since = np.array([t_conf.get(int(i), -(2**62)) for i in ent_id], dtype=np.int64)
    keep = t_ns >= since
    xyz = np.column_stack([st["x"], st["y"], st["z"]]).astype(np.float64).reshape(-1, 3)
    vxy = np.column_stack([st["vx"], st["vy"]]).astype(np.float64).reshape(-1, 2)
    return KDRun(
        np.asarray(s["t_ns"], dtype=np.int64), T, ent_id[keep], t_ns[keep], xyz[keep],
        vxy[keep], classes,
    )  # fmt: skip


# --- one scored time -----------------------------------------------------------------------


@dataclass
class FrameData:
    """Everything scored at one time ``t_ns``, in body frames (xy m).

    Truth boxes (M): ``oid`` (M,) int64, ``ocls`` class names, ``oxy`` (M, 2) centres in the
    TRUE body frame, ``olw`` (M, 2) length/width, ``oyaw`` (M,) rad in the true body frame,
    ``ospeed`` (M,) true horizontal speed m/s, ``orange`` (M,) footprint distance from the body
    origin, ``opoints`` (M,) LADAR returns in the grown box (-1: no sweep).
    Hypotheses (H): ``hid`` (H,), ``hxy`` (H, 2) in the ESTIMATED body frame, ``hspeed`` (H,)
    KD horizontal speed m/s (NaN unknown)."""

    t_ns: int
    oid: np.ndarray
    ocls: list[str]
    oxy: np.ndarray
    olw: np.ndarray
    oyaw: np.ndarray
    ospeed: np.ndarray
    orange: np.ndarray
    opoints: np.ndarray
    hid: np.ndarray
    hxy: np.ndarray
    hspeed: np.ndarray


def hypotheses_at(
    run: KDRun, t_ns: int, T_odom_body: np.ndarray, window_ns: int, lead_ns: int = 0
) -> tuple:
    """Each scored entity's latest state in ``(t_ns - window_ns, t_ns + lead_ns]``, as stored
    (What Is does not predict), moved into the estimated body frame: ids (H,), xy (H, 2) m,
    horizontal speed (H,) m/s.

    ``lead_ns``: the self pose of a cycle is stamped at its sweep's middle and the objects of
    that sweep at their returns' own times, up to half a sweep later; those states belong to
    the cycle scored at ``t_ns`` (:func:`sweep_lead_ns`)."""
    sel = np.flatnonzero((run.t_ns > t_ns - window_ns) & (run.t_ns <= t_ns + lead_ns))
    if not len(sel):
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0)
    # rows are in time order per entity: the last row of each entity is its latest state
    ids = run.ent_id[sel]
    last = sel[np.r_[ids[1:] != ids[:-1], True]]
    p_body = transform_points(se3_inverse(T_odom_body), run.xyz[last])
    return run.ent_id[last], p_body[:, :2], np.hypot(run.vxy[last, 0], run.vxy[last, 1])


def sweep_lead_ns(self_t_ns: np.ndarray) -> int:
    """Half the median spacing of the KD's self times (int64 ns; 0 for fewer than two): how far
    after a cycle's self time (its sweep's middle) the object states of that sweep reach."""
    if len(self_t_ns) < 2:
        return 0
    return int(np.median(np.diff(np.asarray(self_t_ns, dtype=np.int64))) // 2)


def points_in_boxes(
    p: np.ndarray, centers: np.ndarray, sizes: np.ndarray, yaws: np.ndarray, grow_m: float
) -> np.ndarray:
    """How many of the points ``p`` (N, 3) lie in each box (M,), every side grown by
    ``grow_m``; points, centres (M, 3), sizes (M, 3) and yaws (M,) in one frame."""
    out = np.zeros(len(centers), dtype=np.int64)
    half = 0.5 * sizes + grow_m
    reach = np.linalg.norm(half[:, :2], axis=1)
    for k in range(len(centers)):
        d = p - centers[k]
        near = (np.abs(d[:, 0]) <= reach[k]) & (np.abs(d[:, 1]) <= reach[k])
        if not near.any():
            continue
        d = d[near]
        c, s = math.cos(yaws[k]), math.sin(yaws[k])
        u = c * d[:, 0] + s * d[:, 1]
        v = -s * d[:, 0] + c * d[:, 1]
        inside = (np.abs(u) <= half[k, 0]) & (np.abs(v) <= half[k, 1])
        out[k] = int(np.count_nonzero(inside & (np.abs(d[:, 2]) <= half[k, 2])))
    return out


def truth_at(truth: Truth, t_ns: int, config: EvalConfig) -> tuple | None:
    """The truth boxes nearest in time to ``t_ns`` (None when none within ``truth_dt_ns``),
    centres moved by their true velocity over the gap, in the true world frame:
    (boxes, centers (M, 3))."""
    bt = truth.box_t_ns
    k = int(np.argmin(np.abs(bt - t_ns)))
    if abs(int(bt[k]) - t_ns) > config.truth_dt_ns:
        return None
    b = truth.boxes[k]
    dt = (t_ns - b.t_ns) * 1e-9
    return b, b.centers + np.nan_to_num(b.velocities) * dt


def frame_at(
    truth: Truth, run: KDRun, k: int, config: EvalConfig, seen_mid_ns: np.ndarray, lead_ns: int
) -> FrameData | None:
    """The scored data at the KD's k-th self time (None when the truth has no pose or boxes
    there); ``lead_ns`` from :func:`sweep_lead_ns` of the run's self times."""
    t = int(run.self_t_ns[k])
    if not truth.poses.covers(t):
        return None
    got = truth_at(truth, t, config)
    if got is None:
        return None
    boxes, centers = got
    T_body_world = se3_inverse(truth.poses.at(t))
    reach = config.range_m + config.dont_care_band_m
    c_body = transform_points(T_body_world, centers)
    yaw_body = boxes.yaws + math.atan2(T_body_world[1, 0], T_body_world[0, 0])
    body_origin = np.zeros((1, 2))
    range_m = footprint_distance(body_origin, c_body[:, :2], boxes.sizes[:, :2], yaw_body)[:, 0]
    near = np.flatnonzero(range_m < reach)
    pts = np.full(len(near), -1, dtype=np.int64)
    if len(seen_mid_ns) and len(near):
        pts = truth.seen[int(np.argmin(np.abs(seen_mid_ns - t)))].count(boxes.ids[near])
    hid, hxy, hspeed = hypotheses_at(run, t, run.T_odom_body[k], config.state_window_ns, lead_ns)
    return FrameData(
        t, boxes.ids[near], [boxes.classes[i] for i in near], c_body[near, :2],
        boxes.sizes[near, :2], yaw_body[near],
        np.hypot(*np.nan_to_num(boxes.velocities[near, :2]).T).reshape(-1), range_m[near], pts,
        hid, hxy, hspeed,
    )  # fmt: skip


@dataclass
class Filtered:
    """One frame after don't-care removal: what goes to motmetrics.

    ``o`` (M',) indices into the frame's boxes, ``h`` (H',) into its hypotheses, ``dist``
    (M', H') footprint distances m with NaN where a match is not allowed; ``visible`` (M,)
    whether each box of the frame is scored (inside range and seen)."""

    o: np.ndarray
    h: np.ndarray
    dist: np.ndarray
    visible: np.ndarray


def filter_dont_care(fd: FrameData, config: EvalConfig) -> Filtered:
    """Match all boxes and hypotheses first (min-cost assignment over footprint distances at
    most ``match_m``), then remove the don't-care ones: boxes beyond ``range_m`` or seen by
    fewer than ``min_points`` returns are removed with the hypothesis matched to them;
    unmatched hypotheses beyond ``range_m`` are removed. A hypothesis matched to a scored box
    counts wherever its own position lies (a building whose near face is in range has its
    centre beyond it), so range is judged on the box's footprint for both sides of a pair."""
    h_range = np.hypot(fd.hxy[:, 0], fd.hxy[:, 1]) if len(fd.hxy) else np.zeros(0)
    d = footprint_distance(fd.hxy, fd.oxy, fd.olw, fd.oyaw).reshape(len(fd.oid), len(h_range))
    allowed = d <= config.match_m
    seen = (fd.opoints < 0) | (fd.opoints >= config.min_points)
    visible = (fd.orange <= config.range_m) & seen
    pair_o = np.full(len(fd.oid), -1, dtype=np.int64)  # matched hypothesis (column) per box
    if allowed.any():
        cost = np.where(allowed, d, 1e6)
        r, c = linear_sum_assignment(cost)
        ok = allowed[r, c]
        pair_o[r[ok]] = c[ok]
    h_keep = np.ones(len(h_range), dtype=bool)
    h_keep[pair_o[~visible & (pair_o >= 0)]] = False  # matched to a don't-care box
    h_paired = np.zeros(len(h_range), dtype=bool)
    h_paired[pair_o[pair_o >= 0]] = True
    h_keep &= h_paired | (h_range <= config.range_m)  # unmatched and out of range
    o = np.flatnonzero(visible)
    hc = np.flatnonzero(h_keep)
    dist = np.where(allowed[np.ix_(o, hc)], d[np.ix_(o, hc)], np.nan)
    return Filtered(o, hc, dist, visible)


# --- the figures ---------------------------------------------------------------------------


MOT_METRICS = (
    "mota", "motp", "idf1", "precision", "recall", "num_switches", "num_fragmentations",
    "num_detections", "num_false_positives", "num_misses", "num_objects", "num_unique_objects",
)  # fmt: skip


def tracking_scores(
    frames: list[FrameData],
    classes: dict[int, frozenset[str]],
    config: EvalConfig = EvalConfig(),
) -> dict:
    """CLEAR-MOT and identity figures (motmetrics), HOTA (TrackEval, when installed),
    classification accuracy (``classes``: each hypothesis id's predicted class names),
    static-object speed and the number of true persons scored at least once, over
    ``frames``."""
    import motmetrics as mm

    acc = mm.MOTAccumulator(auto_id=False)
    kept: list[tuple[FrameData, Filtered]] = []
    persons_seen: set[int] = set()
    for n, fd in enumerate(frames):
        f = filter_dont_care(fd, config)
        acc.update(fd.oid[f.o].tolist(), fd.hid[f.h].tolist(), f.dist, frameid=n)
        kept.append((fd, f))
        person = np.array([c == "person" for c in fd.ocls], dtype=bool).reshape(-1)
        persons_seen |= {int(i) for i in fd.oid[person & f.visible]}
    out: dict[str, float] = {"frames": float(len(frames))}
    s = mm.metrics.create().compute(acc, metrics=list(MOT_METRICS), name="run").iloc[0]
    for k in MOT_METRICS:
        out[k] = float(s[k])
    tp = out["num_detections"]
    out["switches_per_100"] = 100.0 * out["num_switches"] / tp if tp else math.nan
    out["persons_truth"] = float(len(persons_seen))
    out.update(_pair_figures(acc, kept, classes, config))
    out["hota"] = hota(kept, config)
    return out


def _pair_figures(
    acc: Any,
    kept: list[tuple[FrameData, Filtered]],
    classes: dict[int, frozenset[str]],
    config: EvalConfig,
) -> dict:
    """Classification accuracy and static speed over the matched pairs motmetrics found."""
    ev = acc.mot_events
    tp = ev[ev["Type"].isin(["MATCH", "SWITCH"])]
    right = total = 0
    speeds: list[float] = []
    for (frame, _), row in zip(tp.index, tp.itertuples(index=False), strict=True):
        fd, _f = kept[int(frame)]
        oi = int(np.flatnonzero(fd.oid == int(row.OId))[0])
        hi = int(np.flatnonzero(fd.hid == int(row.HId))[0])
        total += 1
        right += int(fd.ocls[oi] in classes.get(int(row.HId), frozenset()))
        if fd.ospeed[oi] < config.static_speed_mps and np.isfinite(fd.hspeed[hi]):
            speeds.append(float(fd.hspeed[hi]))
    by_class = _recall_by_class(ev, kept)
    by_range = _recall_by_range(ev, kept, config)
    by_phase = _recall_by_phase(ev, kept, config)
    return {
        **by_class,
        **by_range,
        **by_phase,
        "tp_pairs": float(total),
        "classification_accuracy": right / total if total else math.nan,
        "static_pairs": float(len(speeds)),
        "static_speed_median_mps": float(np.median(speeds)) if speeds else math.nan,
        "static_speed_mean_mps": float(np.mean(speeds)) if speeds else math.nan,
    }


def _box_events(
    ev: Any, kept: list[tuple[FrameData, Filtered]]
) -> Iterator[tuple[FrameData, int, bool]]:
    """Each scored box-frame of motmetrics' events (``MATCH``, ``SWITCH`` or ``MISS``): its
    frame's data, the box's index in it, and whether it was matched."""
    for (frame, _), row in zip(ev.index, ev.itertuples(index=False), strict=True):
        if row.Type not in ("MATCH", "SWITCH", "MISS"):
            continue
        fd, _f = kept[int(frame)]
        yield fd, int(np.flatnonzero(fd.oid == int(row.OId))[0]), row.Type != "MISS"


def _recall_by_class(ev: Any, kept: list[tuple[FrameData, Filtered]]) -> dict[str, float]:
    """``recall_<class>``: the fraction of scored box-frames of each true class that were
    matched (motmetrics' MATCH or SWITCH events against its MISS events)."""
    hit: dict[str, int] = {}
    n: dict[str, int] = {}
    for fd, oi, matched in _box_events(ev, kept):
        c = fd.ocls[oi]
        n[c] = n.get(c, 0) + 1
        hit[c] = hit.get(c, 0) + int(matched)
    return {f"recall_{c}": hit[c] / n[c] for c in sorted(n)}


def range_bands(config: EvalConfig) -> list[tuple[float, float]]:
    """The bands of box range (m) recall is given in: ``range_bands_m`` cut [0, range_m]."""
    edges = [0.0, *config.range_bands_m, config.range_m]
    if any(b <= a for a, b in pairwise(edges)):
        raise EvaluationError(
            f"range_bands_m {config.range_bands_m} must rise within (0, {config.range_m})"
        )
    return list(pairwise(edges))


def band_name(lo: float, hi: float) -> str:
    """``"20_30m"`` for the band [20, 30) m."""
    return f"{lo:g}_{hi:g}m"


def _recall_by_range(
    ev: Any, kept: list[tuple[FrameData, Filtered]], config: EvalConfig
) -> dict[str, float]:
    """``recall_<band>`` and ``box_frames_<band>``: of the scored box-frames whose box lies
    in each band of range (:func:`range_bands`, the box's footprint distance from the body),
    the fraction matched and their number. Far objects are met by fewer rows, so this says
    where detection gives out; the counts let a sweep pool the bands over its seeds."""
    bands = range_bands(config)
    top = np.array([hi for _, hi in bands[:-1]])
    return _recall_by_bucket(
        ev, kept, [band_name(lo, hi) for lo, hi in bands],
        lambda fd, oi: int(np.searchsorted(top, fd.orange[oi], side="right")),
    )  # fmt: skip


#: the phases of a log recall is given for (:func:`_recall_by_phase`)
PHASES = ("startup", "steady")


def _recall_by_phase(
    ev: Any, kept: list[tuple[FrameData, Filtered]], config: EvalConfig
) -> dict[str, float]:
    """``recall_startup`` and ``recall_steady``, with ``box_frames_startup`` and
    ``box_frames_steady``: of the scored box-frames in the first ``startup_s`` after the
    log's first scored time and of those after, the fraction matched and their number. At the
    start every object in range is new and is missed until its track is confirmed (three
    sweeps or more); later most are confirmed while still out of range. So the start weighs
    on a short log's recall as it does not on a long one's, and this says how much."""
    if not config.startup_s >= 0:  # NaN too
        raise EvaluationError(f"startup_s {config.startup_s} is not >= 0")
    end_ns = kept[0][0].t_ns + round(config.startup_s * 1e9) if kept else 0
    return _recall_by_bucket(ev, kept, list(PHASES), lambda fd, _oi: int(fd.t_ns >= end_ns))


def _recall_by_bucket(
    ev: Any,
    kept: list[tuple[FrameData, Filtered]],
    names: list[str],
    bucket: Callable[[FrameData, int], int],
) -> dict[str, float]:
    """``recall_<name>`` and ``box_frames_<name>`` of each bucket ``names[i]`` the scored
    box-frames fall in by ``bucket(frame, box index) -> i`` (NaN recall where none)."""
    hit = np.zeros(len(names), dtype=np.int64)
    n = np.zeros(len(names), dtype=np.int64)
    for fd, oi, matched in _box_events(ev, kept):
        b = bucket(fd, oi)
        n[b] += 1
        hit[b] += int(matched)
    out: dict[str, float] = {}
    for name, h, k in zip(names, hit, n, strict=True):
        out[f"recall_{name}"] = h / k if k else math.nan
        out[f"box_frames_{name}"] = float(k)
    return out


def hota(kept: list[tuple[FrameData, Filtered]], config: EvalConfig) -> float:
    """HOTA (TrackEval, averaged over its 19 thresholds) with similarity ``1 - d / match_m``
    (1 inside a footprint, 0 at ``match_m``); NaN when TrackEval is not installed."""
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # it reports optional datasets it lacks
            from trackeval.metrics import HOTA
    except ImportError:
        return math.nan
    gt_map: dict[int, int] = {}
    tr_map: dict[int, int] = {}
    data: dict[str, Any] = {"gt_ids": [], "tracker_ids": [], "similarity_scores": []}
    for fd, f in kept:
        g = np.array([gt_map.setdefault(int(i), len(gt_map)) for i in fd.oid[f.o]], np.int64)
        h = np.array([tr_map.setdefault(int(i), len(tr_map)) for i in fd.hid[f.h]], np.int64)
        data["gt_ids"].append(g)
        data["tracker_ids"].append(h)
        data["similarity_scores"].append(
            np.clip(1.0 - np.nan_to_num(f.dist, nan=np.inf) / config.match_m, 0.0, 1.0)
        )
    data["num_gt_ids"], data["num_tracker_ids"] = len(gt_map), len(tr_map)
    data["num_gt_dets"] = int(sum(len(g) for g in data["gt_ids"]))
    data["num_tracker_dets"] = int(sum(len(h) for h in data["tracker_ids"]))
    res = HOTA().eval_sequence(data)
    return float(np.mean(res["HOTA"]))


def trajectory_scores(
    t_ns: np.ndarray, T_est: np.ndarray, T_true: np.ndarray, delta_m: float = 10.0
) -> dict:
    """Odometry figures with evo over poses (K, 4, 4) at ``t_ns`` (K,): APE translation RMSE m
    after SE(3) Umeyama alignment (no scale; NaN when the positions lie on one line); RPE
    translation mean over ``delta_m`` segments as % of ``delta_m`` (no alignment: relative;
    NaN for a path shorter than one segment); endpoint drift, the final position error after
    aligning the first poses (``align_origin``), as % of the true path length."""
    import copy

    from evo.core import metrics, sync
    from evo.core.filters import FilterException
    from evo.core.geometry import GeometryException
    from evo.core.trajectory import PoseTrajectory3D

    ts = np.asarray(t_ns, dtype=np.float64) * 1e-9
    ref = PoseTrajectory3D(poses_se3=list(T_true), timestamps=ts)
    est = PoseTrajectory3D(poses_se3=list(T_est), timestamps=ts.copy())
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.001)
    out: dict[str, float] = {"path_m": float(ref.path_length)}
    aligned = copy.deepcopy(est)
    try:
        aligned.align(ref, correct_scale=False)
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((ref, aligned))
        out["ape_rmse_m"] = float(ape.get_statistic(metrics.StatisticsType.rmse))
    except GeometryException:  # positions on a line or a point: the alignment is not unique
        out["ape_rmse_m"] = math.nan
    try:
        rpe = metrics.RPE(
            metrics.PoseRelation.translation_part, delta=delta_m, delta_unit=metrics.Unit.meters,
            all_pairs=False,
        )  # fmt: skip
        rpe.process_data((ref, est))
        out["rpe_pct"] = 100.0 * float(rpe.get_statistic(metrics.StatisticsType.mean)) / delta_m
    except (metrics.MetricsException, FilterException):  # a path shorter than one segment
        out["rpe_pct"] = math.nan
    origin = copy.deepcopy(est)
    origin.align_origin(ref)
    end = float(np.linalg.norm(origin.positions_xyz[-1] - ref.positions_xyz[-1]))
    out["final_error_m"] = end
    out["drift_pct"] = 100.0 * end / out["path_m"] if out["path_m"] > 0 else math.nan
    return out


def evaluate_run(truth: Truth, run: KDRun, config: EvalConfig = EvalConfig()) -> dict:
    """Every figure of one run (docs/evaluation.md): tracking over the KD's self times, the
    trajectory over those of them the truth covers."""
    seen_mid = np.array([s.mid_ns for s in truth.seen], dtype=np.int64)
    lead_ns = sweep_lead_ns(run.self_t_ns)
    frames = []
    for k in range(len(run.self_t_ns)):
        fd = frame_at(truth, run, k, config, seen_mid, lead_ns)
        if fd is not None:
            frames.append(fd)
    if not frames:
        raise EvaluationError("no KD self time has truth (poses and boxes) to score against")
    out = tracking_scores(frames, run.classes, config)
    ok = np.array([truth.poses.covers(int(t)) for t in run.self_t_ns])
    T_true = np.stack([truth.poses.at(int(t)) for t in run.self_t_ns[ok]])
    traj = trajectory_scores(run.self_t_ns[ok], run.T_odom_body[ok], T_true, config.rpe_delta_m)
    out.update(traj)
    out["persons_kd"] = float(len(run.person_ids))
    out["person_count_error"] = abs(out["persons_kd"] - out["persons_truth"])
    return out


def evaluate_files(log_path: str | Path, kd_path: str | Path, config: EvalConfig = EvalConfig()):
    """Every figure of the KD file ``kd_path`` (opened read-only) against the truth in the log
    ``log_path``: a dict name -> float (units in docs/evaluation.md)."""
    return evaluate_run(load_truth(log_path, config), load_kd(kd_path, config), config)
