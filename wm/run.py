"""The main job: a log through the world-modeling node into a KD, with a summary and pictures.

``run_log(log, kd_path)`` reads any supported log (logs.open_log), feeds every frame to a
:class:`~wm.node.WorldModelNode`, scores against the log's ground truth when it has some
(:mod:`wm.truth` for odometry and maps, :mod:`wm.evaluation` for the KD's entities), flushes
the KD and returns a :class:`RunReport` (also written as JSON).
With a KD file, map tiles leaving the windows (and the last windows) are kept in it
(:mod:`wm.tiles`), and a later run over the same file starts from them.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import kd_store
from core.geometry import NS_PER_S
from kd_store.persist import snapshot_target
from logs import LogSource, open_log
from logs.prefetch import FramePrefetcher
from logs.types import CameraFrame, LadarScan, LogMessage, ObjectBoxes, OdometryFrame
from wm.config import NodeConfig, PoseSource
from wm.engine_config import EngineConfig
from wm.node import WorldModelNode
from wm.tiles import keep_windows, map_stack_over_kd
from wm.truth import OdometryScore, RasterTruth, TerrainTruth, elevation_error

log = logging.getLogger(__name__)


@dataclass
class RunReport:
    """What a run did and how well (every field JSON-ready)."""

    log: str
    kd: str
    pose_source: str
    frames: dict[str, int]
    sweeps: int
    duration_s: float
    wall_s: float
    missing: list[str]
    notes: list[str]
    entities: dict[str, dict[str, int]]
    events: dict[str, int]
    stage_ms_per_sweep: dict[str, float]
    odometry_status: dict[str, int]
    #: frames lost, per reason, each counted once: those the node refused (bad pose, out of
    #: order, time jump, bad shape) and the messages the log reader left out with
    #: ``--skip-corrupt`` (duplicated chunk, corrupt chunk, duplicated message, ...)
    skipped: dict[str, int] = field(default_factory=dict)
    #: what the node did about the log on its own, per named reason (time_jump_new_segment)
    node_events: dict[str, int] = field(default_factory=dict)
    #: CPU ms per sweep: the node's stages (its thread), ``read`` (decoding the log),
    #: ``odometry`` (the odometry process, when it runs in one) and ``main_process`` (every
    #: thread of this process over the whole run, start-up included)
    cpu_ms_per_sweep: dict[str, float] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    pictures: list[str] = field(default_factory=list)
    #: the KD file's periodic flush: ``interval_s`` (log s, NodeConfig.kd_flush_every_ns),
    #: ``max_lag_s`` (the longest the file stayed behind the log, log s: the newest frame's
    #: time less the last flushed sweep's, just before each flush) and ``flushes`` (count,
    #: the final one included)
    kd_flush: dict[str, float] = field(default_factory=dict)
    #: read-only snapshots of the KD (``--snapshot``, NodeConfig.snapshot_path): ``path``,
    #: ``interval_s`` (log s), ``published`` (count, the final one included), ``failed`` and
    #: the wall time each took, ``median_ms`` and ``max_ms`` (flush, CHECKPOINT, copy, rename);
    #: empty without snapshots
    kd_snapshot: dict[str, Any] = field(default_factory=dict)
    #: rows in the KD at the end: the vehicle's states and the entity frames (self included)
    self_states: int = 0
    kd_entities: int = 0

    @property
    def real_time_factor(self) -> float:
        """Log seconds per wall second (> 1: faster than real time)."""
        return self.duration_s / self.wall_s if self.wall_s > 0 else float("inf")

    def to_json(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["real_time_factor"] = self.real_time_factor
        return _jsonable(d)

    def text(self) -> str:
        """The summary a user reads."""
        lines = [
            f"log {self.log}: {self.duration_s:.1f} s, {self.sweeps} sweeps, "
            f"{sum(self.frames.values())} frames ({_fmt_counts(self.frames)})",
            f"KD {self.kd}; poses from {self.pose_source} ({_fmt_counts(self.odometry_status)})",
            f"wall {self.wall_s:.1f} s: {self.real_time_factor:.2f}x real time",
            "ms per sweep: "
            + _fmt_counts({k: f"{v:.1f}" for k, v in self.stage_ms_per_sweep.items()}),
            "CPU ms per sweep: "
            + _fmt_counts({k: f"{v:.1f}" for k, v in self.cpu_ms_per_sweep.items()}),
        ]
        if self.skipped:
            lines.append(f"skipped (logged): {_fmt_counts(self.skipped)}")
        if self.node_events:
            lines.append(f"node events: {_fmt_counts(self.node_events)}")
        for m in self.missing:
            lines.append(f"missing: {m}")
        for n in self.notes:
            lines.append(f"note: {n}")
        for cls, by_status in sorted(self.entities.items()):
            lines.append(f"entities {cls}: {_fmt_counts(by_status)}")
        lines.append(f"events: {_fmt_counts(self.events) or 'none'}")
        for k, v in self.metrics.items():
            lines.append(f"{k}: {_fmt_counts(v) if isinstance(v, dict) else v}")
        if self.kd_flush:
            f = self.kd_flush
            lines.append(
                f"KD flushes: {f['flushes']}, every {f['interval_s']:g} s of log; the file "
                f"was at most {f['max_lag_s']:.2f} s behind the log"
            )
        if self.kd_snapshot:
            s = self.kd_snapshot
            lines.append(
                f"KD snapshots: {s['published']} published to {s['path']} (every "
                f"{s['interval_s']:g} s of log), {s['median_ms']:.1f} ms median, "
                f"{s['max_ms']:.1f} ms max" + (f"; {s['failed']} failed" if s["failed"] else "")
            )
        for p in self.pictures:
            lines.append(f"picture {p}")
        return "\n".join(lines)


def _fmt_counts(d: dict) -> str:
    return ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in d.items())


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v


def missing_inputs(frames: Counter, uses_odometry: bool = True) -> list[str]:
    """What the log lacks, said plainly (the run goes on with what it has)."""
    out = []
    if not frames[LadarScan.__name__]:
        out.append("no LADAR sweeps: nothing to map or perceive")
    if not frames[OdometryFrame.__name__] and uses_odometry:
        out.append("no wheel odometry: poses from LADAR registration alone")
    if not frames[CameraFrame.__name__]:
        out.append("no camera: SP runs on LADAR only")
    if not frames[ObjectBoxes.__name__]:
        out.append("no ground-truth objects: no detection scores")
    return out


def run_log(
    log_path: str | Path,
    kd_path: str | Path = ":memory:",
    *,
    config: EngineConfig | NodeConfig | None = None,
    report_path: str | Path | None = None,
    render_dir: str | Path | None = None,
    progress: bool = True,
    seconds: float | None = None,
    decode_process: bool = False,
    skip_corrupt: bool = False,
) -> RunReport:
    """Run the node over a whole log (or its first ``seconds``); see the module docstring.
    With ``decode_process`` the log is decoded ahead in a child interpreter
    (:class:`~logs.prefetch.FramePrefetcher`), which takes its few ms per sweep off the
    node's process (``wm run`` does this unless told ``--decode-in-process``); off here by
    default, since a child's start-up (about 0.3 s) outweighs it on short logs.

    With ``skip_corrupt`` corrupt and duplicated records of the log are skipped and counted
    in the report's ``skipped`` (as the messages lost, per reason) instead of stopping the
    run. Damaged truth that only scores the run (the terrain attachment or its metadata)
    never stops it: that score is left out and a note says why."""
    engine = EngineConfig.of(config)
    config = engine.node
    source = open_log(Path(log_path), skip_corrupt=skip_corrupt)
    info = source.info()
    total = sum(t.count for t in info.topics)
    terrain, no_terrain = _terrain_truth(source)
    terrain = terrain or RasterTruth.from_folder(Path(log_path))
    if str(kd_path) != ":memory:":
        Path(kd_path).parent.mkdir(parents=True, exist_ok=True)
    if config.snapshot_path is not None:  # refused before the KD file is made
        snapshot_target(kd_path, config.snapshot_path)
    t_start, cpu_start = time.perf_counter(), time.process_time()
    read_cpu_s = [0.0]
    with (
        compute_threads(config.compute_threads),
        _reader(source, decode_process) as (frames_in, reader),
        kd_store.open(kd_path, engine.kd, run="new", source=str(log_path)) as kd,
    ):
        # map tiles in the KD (in memory: the node's own stack)
        stack = map_stack_over_kd(kd, engine.maps) if str(kd_path) != ":memory:" else None
        node = WorldModelNode(kd, engine, stack)
        odo = OdometryScore()
        first_t, last_t = None, None
        frames = _cpu_timed(frames_in, read_cpu_s)
        lines = FlushLines(progress and not sys.stderr.isatty(), Path(log_path).name)
        # on an error (a bad log, Ctrl-C) the node flushes what the KD holds before the KD
        # closes, and its odometry process stops (no orphan, no hang)
        with node:
            for frame in _progress(frames, total, progress, Path(log_path).name):
                first_t = frame.t_ns if first_t is None else first_t
                if seconds is not None and frame.t_ns - first_t > seconds * NS_PER_S:
                    break
                last_t = frame.t_ns
                for c in node.feed(frame):
                    _score(node, c, odo)
                lines.after(node, first_t)
            for c in node.finish():
                _score(node, c, odo)
        if stack is not None:
            keep_windows(stack)  # the last windows too, for the next run over this KD
            node.publish_snapshot()  # ... and in the snapshot
        wall = time.perf_counter() - t_start
        report = _report(node, kd, log_path, kd_path, first_t, last_t, wall)
        n = max(node.stats.sweeps, 1)
        report.cpu_ms_per_sweep = {
            **{k: 1e3 * v / n for k, v in node.stats.stage_cpu_s.items()},
            "read": 1e3 * read_cpu_s[0] / n,
            "main_process": 1e3 * (time.process_time() - cpu_start) / n,
        }
        if reader is not None and reader.decode_cpu_s:
            report.cpu_ms_per_sweep["decode_process"] = 1e3 * reader.decode_cpu_s / n
        report.metrics.update(_metrics(node, odo, terrain))
        if no_terrain is not None:
            report.metrics["elevation"] = {"disabled": no_terrain}
            report.notes.append(f"elevation scores disabled: {no_terrain}")
        _log_losses(report, source)
        report.metrics.update(_tracking(node, kd, log_path, skip_corrupt))
        if render_dir is not None:
            from wm.render import render_run

            report.pictures = [str(p) for p in render_run(node, Path(render_dir))]
    if report_path is not None:
        Path(report_path).parent.mkdir(parents=True, exist_ok=True)
        Path(report_path).write_text(json.dumps(report.to_json(), indent=2))
    return report


@contextmanager
def compute_threads(n: int | None) -> Iterator[None]:
    """BLAS and OpenMP libraries limited to ``n`` threads inside the block (None: no limit);
    the previous limits come back after it."""
    if n is None:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=n):
        yield


@contextmanager
def _reader(
    source: LogSource, decode_process: bool
) -> Iterator[tuple[Iterator[LogMessage], FramePrefetcher | None]]:
    """The log's frames, decoded here or ahead in a child process (stopped on leaving)."""
    if not decode_process:
        yield source.frames(), None
        return
    with FramePrefetcher(source) as prefetcher:
        yield iter(prefetcher), prefetcher


def _cpu_timed(frames: Iterator[LogMessage], total_s: list[float]) -> Iterator[LogMessage]:
    """The frames, adding the CPU time (this thread) spent producing them to ``total_s[0]``."""
    it = iter(frames)
    while True:
        t = time.thread_time()
        try:
            frame = next(it)
        except StopIteration:
            total_s[0] += time.thread_time() - t
            return
        total_s[0] += time.thread_time() - t
        yield frame


def _terrain_truth(source: LogSource) -> tuple[TerrainTruth | None, str | None]:
    """The log's terrain truth (None if it has none), and why it is unusable when it is
    there but damaged (a CRC mismatch, bytes that are no array, metadata that is no grid). It
    only scores the run, so a damaged one is left out with a warning, never fatal."""
    damaged = {k: v for k, v in _safe(source.damaged_extras).items() if _terrain_related(k)}
    try:
        truth = TerrainTruth.from_log(_safe(source.attachments), _safe(source.metadata))
    except Exception as e:
        why = f"terrain truth in the log is unusable ({type(e).__name__}: {e})"
    else:
        if truth is not None or not damaged:
            return truth, None
        why = "terrain truth in the log is damaged: " + "; ".join(damaged.values())
    log.warning("%s; the run is not scored on it", why)
    return None, why


def _terrain_related(what: str) -> bool:
    """A damaged attachment or metadata record that may be the terrain truth (a damaged
    metadata record's name is unknown)."""
    return "terrain" in what or "METADATA" in what


def _log_losses(report: RunReport, source: LogSource) -> None:
    """The messages the reader left out (``--skip-corrupt``), per reason, into the report's
    ``skipped``, and what it noted into its notes: each once (the reader counts a record
    once however many passes meet it)."""
    for reason, n in source.stats.lost.items():
        report.skipped[reason] = report.skipped.get(reason, 0) + n
    report.notes += [m for m in source.stats.messages if m not in report.notes]


def _node_skips(stats) -> dict[str, int]:
    """The node's skipped frames per reason, and the points it dropped from sweeps it took
    (non-finite or out of range) under "non-finite points" (a count of points, not frames)."""
    out = dict(stats.skipped)
    if stats.dropped_nonfinite_points:
        out["non-finite points"] = stats.dropped_nonfinite_points
    return out


def _safe(get) -> dict:
    try:
        return get()
    except Exception:  # a log format without attachments or metadata
        return {}


class FlushLines:
    """Progress where no progress bar shows (stderr is a file or a pipe: a service log, a
    batch job): one line each time the node flushes the KD, which is every second of log
    time, saying up to when the file holds the run, so that whoever reads the log after a
    crash knows what the KD kept."""

    def __init__(self, show: bool, name: str) -> None:
        self.show, self.name = show, name
        self.last: int | None = None
        self.t0 = time.perf_counter()

    def after(self, node: WorldModelNode, first_t_ns: int | None) -> None:
        """Print a line if the node flushed since the last one."""
        t = node.flushed_t_ns
        if not self.show or t is None or t == self.last or first_t_ns is None:
            return
        self.last = t
        print(
            f"wm run {self.name}: KD flushed to t_ns={t} ({(t - first_t_ns) / NS_PER_S:.1f} s "
            f"of log, {node.stats.sweeps} sweeps, {time.perf_counter() - self.t0:.1f} s wall)",
            file=sys.stderr,
            flush=True,
        )


def _progress(frames, total: int, show: bool, name: str):
    if not show:
        return frames
    from tqdm import tqdm

    tty = sys.stderr.isatty()
    return tqdm(frames, total=total, unit="msg", desc=f"wm run {name}", disable=not tty)


def _score(node: WorldModelNode, cycle, odo: OdometryScore) -> None:
    if node.truth.t_ns:
        odo.add(cycle.t_pose_ns, cycle.T_world_body, node.truth)


def _tracking(
    node: WorldModelNode, kd: kd_store.KnowledgeDatabase, log_path, skip_corrupt: bool = False
) -> dict[str, Any]:
    """The KD's object entities against the log's truth, as `wm evaluate` scores them
    (:mod:`wm.evaluation`, docs/evaluation.md: py-motmetrics, TrackEval, evo), once the run is
    over: the log is read again for its truth, off the node's time. Empty when SP did not run
    or the log has no true poses and boxes."""
    if node.sp is None or not node.truth.t_ns or not node.stats.frames[ObjectBoxes.__name__]:
        return {}
    from wm.evaluation import EvaluationError, evaluate_run, load_kd, load_truth

    kd.flush()
    try:
        s = evaluate_run(load_truth(log_path, skip_corrupt=skip_corrupt), load_kd(kd))
    except EvaluationError as e:
        return {"detection": {"error": str(e)}}
    return {"detection": {k: s[k] for k in REPORTED_TRACKING if k in s}}


#: the scores of :mod:`wm.evaluation` a run's report carries (``wm evaluate`` prints them all)
REPORTED_TRACKING = (
    "precision", "recall", "mota", "idf1", "hota", "switches_per_100",
    "classification_accuracy", "static_speed_median_mps", "static_speed_mean_mps",
    "person_count_error",
)  # fmt: skip


def _report(node, kd, log_path, kd_path, first_t, last_t, wall) -> RunReport:
    entities: dict[str, Counter] = {}
    for f in kd.entities():
        if f.id == node.self_id:
            continue
        entities.setdefault(f.most_specific_class or "unclassified", Counter())[f.status.value] += 1
    events = Counter(e.class_name for e in kd.events())
    # what the KD file holds (kd.sql flushes first), not only what the node kept in RAM
    in_kd = kd.sql(
        f"SELECT (SELECT count(*) FROM entity_states WHERE entity_id = {node.self_id}) AS self, "
        f"(SELECT count(*) FROM entities WHERE {kd.run_filter()}) AS entities"
    ).to_pylist()[0]
    n = max(node.stats.sweeps, 1)
    duration = (last_t - first_t) / NS_PER_S if first_t is not None and last_t is not None else 0.0
    return RunReport(
        log=str(log_path),
        kd=str(kd_path),
        pose_source=str(node.config.pose_source),
        frames=dict(node.stats.frames),
        sweeps=node.stats.sweeps,
        duration_s=duration,
        wall_s=wall,
        missing=missing_inputs(node.stats.frames, node.config.pose_source == "odometry"),
        notes=list(dict.fromkeys(node.stats.notes)),
        entities={k: dict(v) for k, v in entities.items()},
        events=dict(events),
        stage_ms_per_sweep={k: 1e3 * v / n for k, v in node.stats.stage_s.items()},
        odometry_status=dict(node.stats.odometry_status),
        skipped=_node_skips(node.stats),
        node_events=dict(node.stats.events),
        kd_flush={
            "interval_s": node.config.kd_flush_every_ns / NS_PER_S,
            "max_lag_s": node.stats.kd_flush_max_lag_ns / NS_PER_S,
            "flushes": node.stats.kd_flushes,
        },
        kd_snapshot=_snapshot_summary(node),
        self_states=int(in_kd["self"]),
        kd_entities=int(in_kd["entities"]),
    )


def _snapshot_summary(node: WorldModelNode) -> dict[str, Any]:
    """The report's ``kd_snapshot`` (RunReport): count and wall ms of the snapshots."""
    if node.config.snapshot_path is None:
        return {}
    ms = node.stats.snapshot_ms
    return {
        "path": node.config.snapshot_path,
        "interval_s": node.config.snapshot_every_s,
        "published": len(ms),
        "failed": node.stats.snapshot_failures,
        "median_ms": float(np.median(ms)) if ms else 0.0,
        "max_ms": max(ms, default=0.0),
    }


def _metrics(node, odo: OdometryScore, terrain) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if odo.errors_m:
        out["odometry"] = odo.summary()
    T_align = odo.T_align if node.config.pose_source == PoseSource.ODOMETRY else None
    if terrain is not None and node.stats.sweeps:
        for name in ("primitive", "subsystem"):
            if any(lv.name == name for lv in node.stack.levels):
                level = node.stack.level(name)
                # the map's world aligned to the truth's at the first pose (drift included)
                out[f"elevation_{name}"] = elevation_error(level, terrain, T_align)
                if odo.T_true_est is not None:  # the same map, without the odometry's drift
                    out[f"elevation_{name}_local"] = elevation_error(level, terrain, odo.T_true_est)
    if node.stats.range_image_error_m:
        out["prediction"] = {
            "range_median_abs_error_m": float(np.median(node.stats.range_image_error_m)),
            "surprise_fraction": float(np.mean(node.stats.surprise_fraction)),
            "comparisons": len(node.stats.range_image_error_m),
        }
    return out


def run_node(
    log_path: str | Path,
    kd_path: str | Path = ":memory:",
    config: EngineConfig | NodeConfig | None = None,
    seconds: float | None = None,
) -> WorldModelNode:
    """Feed a log (or its first ``seconds``) through a node and return it, its KD still open
    (the caller closes ``node.kd``): for What If / render from the shell and for tests. A KD
    file gets the map tiles and the final windows, as after :func:`run_log`."""
    source = open_log(Path(log_path))
    engine = EngineConfig.of(config)
    config = engine.node
    kd = kd_store.open(kd_path, engine.kd, run="new", source=str(log_path))
    # map tiles in the KD (in memory: the node's own stack)
    stack = map_stack_over_kd(kd, engine.maps) if str(kd_path) != ":memory:" else None
    node = WorldModelNode(kd, engine, stack)
    first_t = None
    try:
        with compute_threads(config.compute_threads), node:  # finishes, or flushes on an error
            for frame in source.frames():
                first_t = frame.t_ns if first_t is None else first_t
                if seconds is not None and frame.t_ns - first_t > seconds * NS_PER_S:
                    break
                node.feed(frame)
    except BaseException:
        kd.close()  # the caller gets no node to close it through
        raise
    if stack is not None:
        keep_windows(stack)
        kd.flush()
    return node
