"""The ``wm`` command line.

    wm simulate SCENARIO --out LOG.mcap [--seconds S] [--seed N]
    wm log-info LOG [--skip-corrupt] [--check]
    wm query KD.duckdb "SELECT ..." [--parquet OUT [--overwrite]] [--max-rows N] [--max-mb MB]
    wm run LOG --kd KD.duckdb [--overwrite | --append] [--report report.json] [--render DIR]
           [--poses odometry|truth] [--skip-corrupt]  (an existing KD only with one of them)
           [--snapshot S.duckdb [--snapshot-every 5]]  (a read-only copy others may open)
           [--config FILE.yaml]  (also serve, whatif, render; KD.config.yaml records the run's,
           which a command over an existing KD reads when --config is not given)
    wm config --default | FILE.yaml                    (the whole configuration as YAML)
    wm check KD.duckdb                                 (integrity: rows point at frames)
    wm whatis KD.duckdb [--entity ID] [--t-ns T]
    wm whatif LOG [--kd KD.duckdb] --waypoints "t,x,y;t,x,y;..." [--seconds S]
    wm whatif --kd KD.duckdb --waypoints "t,x,y;..."   (the maps and entities a run stored)
    wm render LOG --out DIR [--seconds S]
    wm render --kd KD.duckdb OUT_DIR                    (the maps and entities a run stored)
    wm evaluate LOG KD.duckdb [--json OUT]             (scores of a KD against the log's truth)
    wm serve --replay LOG [--rate 1.0] [--kd KD.duckdb] [--host 127.0.0.1] [--port 8765]
             [--snapshot S.duckdb [--snapshot-every 5]]
    wm serve --ingest [--queue 64] [--kd KD.duckdb] ...  (clients POST ROS 2 messages to /v1/ingest)
           [--rate-limit R [--burst N]]  (per client: N requests at once, then R a second)
           [--in-process]  (the node in a thread of the server's process, not a process of its own)
    wm bg --url http://127.0.0.1:8765 --goal X,Y [--token-env VAR] [--period-s 0.5]
          [--cycles N] [--budget-s 1] [--min-clearance-m 0.5] [--level subsystem] [--json]
          [--no-tell] [--config FILE.yaml]  (its planner section; the flags given override it)
          (a planner in its own process over a live node's API; also python -m wm.bg ...)
    wm demo [--out DIR]

Errors a user can cause (an unknown scenario, a corrupt log, a missing file) are printed as one
clear line on stderr with exit status 2; ``--debug`` shows the traceback as well.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from core.errors import EngineError

if TYPE_CHECKING:  # the command line imports the engine's modules only for the commands run
    from kd_store.config import KDConfig
    from wm.config import PlannerConfig
    from wm.engine_config import EngineConfig

EXIT_USER_ERROR = 2
#: ``wm bg``'s planning budget (s, wall clock) unless ``--budget-s`` or the configuration file's
#: ``planner.budget_s`` gives one: over HTTP each batch of plans is a request that waits for
#: the node's cycle in progress, so the in-process planner's 0.2 s would often allow one batch
BG_BUDGET_S = 1.0


class UserError(EngineError):
    """A problem with what the user asked for; printed without a traceback."""


def _user_error_types() -> tuple[type[BaseException], ...]:
    """Exception types that describe bad input: every module's own (one base) and a missing
    file."""
    return (EngineError, FileNotFoundError)


def cmd_simulate(args: argparse.Namespace) -> int:
    from fixtures.simulate import simulate_to_log

    out = Path(args.out)
    if out.suffix != ".mcap":
        raise UserError(f"--out {out}: the simulator writes MCAP logs; give a path ending in .mcap")
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    simulate_to_log(
        args.scenario, out, seconds=args.seconds, seed=args.seed, progress=not args.no_progress
    )
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_log_info(args: argparse.Namespace) -> int:
    """What a log holds; with ``--check`` every frame is decoded and every defect that would
    stop ``wm run`` is listed, one line each (exit status 2 when there is any)."""
    from logs import format_log_info, open_log

    path = Path(args.log)
    if not path.exists():
        raise FileNotFoundError(f"log {path} does not exist")
    # a check reads on past each defect, so that it lists them all
    source = open_log(path, skip_corrupt=args.skip_corrupt or args.check)
    print(format_log_info(source.info()))
    if args.check:  # decode every frame, so dropped points and backwards times are counted
        n = sum(1 for _ in source.frames())
        print(f"checked: {n} frames decoded")
    for name, data in sorted(source.attachments().items()):
        print(f"attachment {name}: {len(data)} bytes")
    for name, values in sorted(source.metadata().items()):
        print(f"metadata {name}: " + ", ".join(f"{k}={v}" for k, v in sorted(values.items())))
    stats = source.stats
    if stats.skipped_records or stats.dropped_nonfinite_points or stats.backwards_timestamps:
        print(
            f"problems: {stats.skipped_records} corrupt records skipped, "
            f"{stats.dropped_nonfinite_points} non-finite points dropped, "
            f"{stats.backwards_timestamps} timestamps going backwards"
        )
        for line in stats.messages:
            print(f"  {line}")
    if not args.check:
        return 0
    defects = list(source.defects) + list(source.damaged_extras().values())
    for d in defects:
        print(f"defect: {d}")
    if defects:
        print(
            f"wm log-info: {path}: {len(defects)} defects (wm run stops at the first log "
            f"defect unless --skip-corrupt; damaged attachments only disable scores)",
            file=sys.stderr,
        )
        return EXIT_USER_ERROR
    print("check: no defects")
    return 0


def format_table(table, max_rows: int = 50) -> str:
    """A pyarrow Table as aligned text, at most ``max_rows`` rows (says how many were left out)."""
    cols = table.column_names
    rows = table.slice(0, max_rows).to_pylist()
    cells = [cols] + [[_cell(r[c]) for c in cols] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(cols))]
    lines = ["  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)) for row in cells]
    if table.num_rows > max_rows:
        lines.append(f"... {table.num_rows - max_rows} more rows")
    lines.append(f"({table.num_rows} rows)")
    return "\n".join(lines)


def _cell(v: object) -> str:
    text = f"{v:.6g}" if isinstance(v, float) else str(v)
    return text if len(text) <= 60 else text[:57] + "..."


def cmd_query(args: argparse.Namespace) -> int:
    """Read-only SQL over a KD file's documented views (entities, entity_states, events, ...)."""
    from kd_store.query import MB, QueryLimits, query_file

    path = Path(args.kd)
    if not path.exists():
        raise FileNotFoundError(f"KD file {path} does not exist")
    out = _parquet_target(args.parquet, path, args.overwrite) if args.parquet else None
    limits = QueryLimits(
        memory_limit=args.memory_limit,
        timeout_s=args.timeout,
        max_rows=args.max_rows,
        max_bytes=round(args.max_mb * MB),
    )
    table = query_file(path, args.sql, limits)
    if out is not None:
        import pyarrow.parquet as pq

        tmp = out.with_name(f".{out.name}.partial")
        pq.write_table(table, tmp)
        tmp.replace(out)  # whole or not at all
        print(f"wrote {table.num_rows} rows to {out}")
    else:
        print(format_table(table, args.show_rows))
    return 0


def _parquet_target(value: str, kd: Path, overwrite: bool = False) -> Path:
    """The Parquet file ``--parquet`` names, refused when it is the KD itself, a folder, a
    file that is not Parquet, or (unless ``overwrite``) any file that exists already: a typo
    cannot overwrite a KD, a log or an earlier result."""
    out = Path(value)
    if out.is_dir():
        raise UserError(f"--parquet {out}: is a folder; give a file name ending in .parquet")
    if out.exists() and out.resolve() == kd.resolve():
        raise UserError(f"--parquet {out}: is the KD being queried; give another file")
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise UserError(f"--parquet {out}: the file exists; give --overwrite to replace it")
    if out.suffix != ".parquet":
        raise UserError(f"--parquet {out}: give a file name ending in .parquet")
    if not out.parent.is_dir():
        raise UserError(f"--parquet {out}: folder {out.parent} does not exist")
    return out


def _recorded_config_path(kd: str | Path) -> Path:
    """Where ``wm run --kd K`` records the configuration it ran with: ``K.config.yaml``."""
    return Path(f"{kd}.config.yaml")


def _config_file(args: argparse.Namespace, kd: str | None = None) -> tuple[Path | None, bool]:
    """The configuration file a command reads, and whether it is the one recorded next to the
    KD: ``--config FILE`` if given, else ``K.config.yaml`` beside an existing KD file ``kd``
    (its map tiles have the geometry of the run that wrote them), else None (the defaults)."""
    given = getattr(args, "config", None)
    if given is not None:
        return Path(given), False
    if kd is None or kd == ":memory:" or not Path(kd).is_file():
        return None, False
    recorded = _recorded_config_path(kd)
    return (recorded, True) if recorded.is_file() else (None, False)


def _engine_config(args: argparse.Namespace, kd: str | None = None):
    """The run's configuration: ``--config FILE`` over the defaults (without it, the
    ``K.config.yaml`` recorded next to an existing KD file ``kd``), then the flags given
    (--poses, --snapshot, --snapshot-every) over that. A file read is named in a note line."""
    from dataclasses import replace

    from wm.config import PoseSource
    from wm.engine_config import EngineConfig

    path, recorded = _config_file(args, kd)
    if path is None:
        engine = EngineConfig()
    else:
        engine = _read_config(path, kd if recorded else None)
        whose = f"recorded with KD {kd}" if recorded else "from --config"
        print(f"note: configuration {path} ({whose})")
    flags = {
        "pose_source": PoseSource(args.poses) if getattr(args, "poses", None) else None,
        "snapshot_path": getattr(args, "snapshot", None),
        "snapshot_every_s": getattr(args, "snapshot_every", None),
    }
    try:
        node = replace(engine.node, **{k: v for k, v in flags.items() if v is not None})
    except ValueError as e:  # a bad --snapshot-every
        raise UserError(str(e)) from None
    return replace(engine, node=node)


def _read_config(
    path: Path, kd: str | None = None, base: EngineConfig | None = None
) -> EngineConfig:
    """The configuration file ``path`` over ``base`` (None: the defaults; ``kd``: the KD it
    was recorded with, if it was), or one :class:`UserError` naming the file when it cannot
    be read or taken."""
    from wm.engine_config import ConfigError, EngineConfig

    flag = f"KD {kd}: its recorded configuration" if kd is not None else "--config"
    try:
        return EngineConfig.from_yaml(path, base)
    except FileNotFoundError:
        raise UserError(f"{flag} {path}: the file does not exist") from None
    except (OSError, UnicodeDecodeError) as e:  # a folder, unreadable, not text
        raise UserError(f"{flag} {path}: cannot be read ({e})") from None
    except ConfigError as e:  # names the file and the dotted key already
        if kd is None:
            raise
        raise UserError(f"{e} (give --config FILE to read KD {kd} with another)") from None


def _record_config(kd: str, config) -> Path | None:
    """Write ``config`` next to the KD file ``kd`` as ``K.config.yaml``, for the commands that
    read the KD later without the log (None for an in-memory KD)."""
    if kd == ":memory:":
        return None
    path = _recorded_config_path(kd)
    path.parent.mkdir(parents=True, exist_ok=True)
    config.to_yaml(path)
    return path


def _check_log(path: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"log {p} does not exist")
    return p


def _kd_target(value: str, overwrite: bool, log: Path, append: bool = False) -> str:
    """The KD file ``wm run --kd`` writes: refused when it exists (a typo must not mix a
    second run into a KD or replace one) unless ``append`` (the run is added as a run of its
    own: ``run_id`` in every view) or ``overwrite``, which removes it and its write-ahead log
    first (a stale ``.wal`` left beside a new file would be replayed into it). Either way a
    file that is not a DuckDB database (the log, by a slip of the shell) is never touched."""
    path = Path(value)
    if value == ":memory:":
        return value
    if overwrite and append:
        raise UserError("--overwrite and --append: give one (replace the KD, or add a run)")
    if path.is_dir():
        raise UserError(f"--kd {path}: is a folder; give a file name")
    if not (path.exists() or path.is_symlink()):
        return value
    if not (overwrite or append):
        raise UserError(
            f"--kd {path}: the file exists; give --append to add this run to it or "
            "--overwrite to replace it"
        )
    flag = "--append" if append else "--overwrite"
    if path.exists() and (path.resolve() == log.resolve() or not _is_duckdb(path)):
        raise UserError(f"--kd {path}: not a DuckDB file; {flag} works only on a KD")
    if append:
        return value
    for stale in (path, Path(f"{path}.wal")):
        stale.unlink(missing_ok=True)
    return value


def _is_duckdb(path: Path) -> bool:
    """The file is empty or starts with DuckDB's header (magic ``DUCK`` at byte 8)."""
    with path.open("rb") as f:
        head = f.read(12)
    return not head or head[8:12] == b"DUCK"


def _produced_nothing(report, log: Path) -> str | None:
    """What a finished run's log lacked, when the run made nothing of it: no LADAR sweep, no
    vehicle pose, or no entity in the KD; None for a run that produced something."""
    if not report.sweeps and report.frames.get("LadarScan"):
        skipped = ", ".join(f"{k}={v}" for k, v in report.skipped.items()) or "none"
        return f"{log}: no usable LADAR sweep of {report.frames['LadarScan']} (skipped: {skipped})"
    if not report.sweeps:
        from logs import open_log

        topics = ", ".join(f"{t.name} ({t.msgtype})" for t in open_log(log).info().topics)
        return f"{log}: no PointCloud2 sweep on any topic; topics are: {topics or 'none'}"
    if not report.self_states:
        return f"{log}: {report.sweeps} sweeps but no vehicle pose came of them"
    if not report.kd_entities:
        return f"{log}: {report.sweeps} sweeps but the KD {report.kd} holds no entity"
    return None


def cmd_run(args: argparse.Namespace) -> int:
    """The main job: a log through the world-modeling node into a KD, summary and report.
    A run that produced nothing (no sweep, pose or entity) is a user error: one line on what
    the log lacked, exit status 2, though the report is still written."""
    from kd_store.persist import snapshot_target
    from wm.run import run_log

    log = _check_log(args.log)
    append = getattr(args, "append", False)
    # a run added to a KD continues its maps: their geometry is the recorded configuration's
    config = _engine_config(args, args.kd if append else None)
    if config.node.snapshot_path is not None:  # refused before --overwrite removes anything
        snapshot_target(args.kd, config.node.snapshot_path)
    kd = _kd_target(args.kd, getattr(args, "overwrite", False), log, append)
    config_path = _record_config(kd, config)  # the configuration it ran with, by its results
    report = run_log(
        log,
        kd,
        config=config,
        report_path=args.report,
        render_dir=args.render,
        progress=not args.no_progress,
        seconds=args.seconds,
        decode_process=not getattr(args, "decode_in_process", False),
        skip_corrupt=getattr(args, "skip_corrupt", False),
    )
    print(report.text())
    if args.report:
        print(f"report {args.report}")
    if config_path is not None:
        print(f"config {config_path}")
    lacked = _produced_nothing(report, log)
    if lacked is not None:
        raise UserError(lacked)
    return 0


def cmd_config(args: argparse.Namespace) -> int:
    """Print a whole configuration as YAML: the defaults (``--default``), or FILE's changes
    over them (which checks FILE), for a file to start from or to see what a run will use."""
    from wm.engine_config import EngineConfig

    if (args.file is None) == (not args.default):
        raise UserError("config: give --default, or a configuration FILE to check and show")
    config = EngineConfig() if args.default else EngineConfig.from_yaml(args.file)
    print(config.to_yaml(), end="")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    """Integrity of a KD file (kd_store.check): rows per table, then each defect; exit status
    2 when there is one (or the file is not a KD), 0 when the file is sound."""
    from kd_store.check import check_file

    result = check_file(args.kd)
    print(f"KD {result.path}: schema version {result.schema_version}")
    for table, n in result.counts.items():
        print(f"  {table}: {n} rows")
    for d in result.defects:
        print(f"defect: {d.text()}")
    if not result.ok:
        print(f"wm check: {len(result.defects)} kinds of defect in {result.path}", file=sys.stderr)
        return EXIT_USER_ERROR
    print("ok: every state, relation and event points at an existing frame; positions finite")
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    """A live node replaying a log at its recorded pace (or fed ROS 2 messages by clients,
    ``--ingest``), serving What Is over HTTP (wm.serve)."""
    import os

    from wm.serve import LiveNode, serve

    token = os.environ.get(args.token_env) if args.token_env else None
    if args.token_env and not token:
        raise UserError(f"--token-env {args.token_env}: that environment variable is empty")
    if args.host not in ("127.0.0.1", "localhost", "::1") and not token:
        print(f"warning: serving on {args.host} without a token", file=sys.stderr)
    limits = _serve_limits(args)
    # a KD file that exists gets one more run, which continues its maps (their geometry is
    # the recorded configuration's)
    config = _engine_config(args, args.kd)
    # the node in a process of its own unless asked: the server's Python work in this process
    # then never takes the node's interpreter lock (wm.serve_proc)
    process = not args.in_process
    if args.ingest:
        from wm.ingest import IngestNode

        live = IngestNode(args.kd, config, args.queue, process=process).start()
        what = f"ROS 2 messages posted to /v1/ingest (queue {args.queue} frames)"
    else:
        live = LiveNode(_check_log(args.replay), args.kd, config, args.rate, process).start()
        what = f"{args.replay} at {args.rate:g}x"
    _record_config(args.kd, config)  # once the KD opened: never beside a file that is no KD
    print(f"serving {what} on http://{args.host}:{args.port}/v1 "
          f"(schema: /openapi.json); KD {args.kd}; Ctrl-C stops")  # fmt: skip
    # SIGTERM (a service manager's stop) ends the server like Ctrl-C: the web server shuts
    # down, then raises the signal again for the handler it found, which must not be the
    # default one (that kills the process before the node flushes and closes the KD)
    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        serve(live, args.host, args.port, token, limits)
    finally:
        live.stop()
        signal.signal(signal.SIGTERM, previous)
    return 0


def _exit_on_sigterm(signum: int, frame: object) -> None:
    """SIGTERM, once the web server has shut down: leave through ``finally`` (the node
    stops, the KD is flushed and closed) with exit status 0, a requested stop."""
    print("wm serve: stopping on SIGTERM", file=sys.stderr)
    raise SystemExit(0)


def cmd_bg(args: argparse.Namespace) -> int:
    """Behavior generation in this process against a live node's HTTP API (wm.remote): one
    line per plan; exit status 2 when the server cannot be reached or refuses a request."""
    import os

    from wm.client import Client
    from wm.remote import check_url, parse_goal, run_bg

    url, goal = check_url(args.url), parse_goal(args.goal)
    for flag, attr, field in _BG_FLAGS:
        v = getattr(args, attr)
        if v is not None and field in _BG_NEEDS and not _bg_value_ok(field, v):
            raise UserError(f"{flag} {v}: need {_BG_NEEDS[field]}")
    if args.cycles is not None and args.cycles < 1:
        raise UserError(f"--cycles {args.cycles}: need at least 1 plan")
    token = os.environ.get(args.token_env) if args.token_env else None
    if args.token_env and not token:
        raise UserError(f"--token-env {args.token_env}: that environment variable is empty")
    config = _planner_config(args)
    made = run_bg(Client(url, token), goal, config, args.cycles, args.json, not args.no_tell)
    ended = args.cycles is None or made < args.cycles  # stopped by the end of the node's log
    print(f"wm bg: {made} plans" + ("; the node's log has ended" if ended else ""),
          file=sys.stderr)  # fmt: skip
    return 0


#: ``wm bg``'s flags over the ``planner`` section: (flag, argparse attribute, PlannerConfig field)
_BG_FLAGS = (
    ("--period-s", "period_s", "replan_period_s"),
    ("--budget-s", "budget_s", "budget_s"),
    ("--min-clearance-m", "min_clearance_m", "min_clearance_m"),
    ("--level", "level", "level"),
)
#: What each checked planner field needs (s, m), as the error says it.
_BG_NEEDS = {
    "replan_period_s": "a finite number of seconds > 0",
    "budget_s": "a finite number of seconds > 0",
    "min_clearance_m": "a finite distance >= 0 m",
}


def _bg_value_ok(field: str, v: float) -> bool:
    """Whether ``v`` is a usable value of the planner field ``field`` (one of _BG_NEEDS)."""
    if field == "min_clearance_m":
        return bool(np.isfinite(v) and v >= 0)
    return bool(np.isfinite(v) and v > 0)


def _planner_config(args: argparse.Namespace) -> PlannerConfig:
    """``wm bg``'s planner: the ``planner`` section of ``--config FILE`` (if given) over the
    defaults with ``budget_s`` :data:`BG_BUDGET_S`, then the flags given over that. A file
    read is named in a note line on stderr (stdout carries the plans)."""
    from dataclasses import replace

    from wm.config import PlannerConfig
    from wm.engine_config import EngineConfig

    base = EngineConfig(planner=replace(PlannerConfig(), budget_s=BG_BUDGET_S))
    path = None if getattr(args, "config", None) is None else Path(args.config)
    engine = base if path is None else _read_config(path, base=base)
    if path is not None:
        print(f"note: configuration {path} (from --config)", file=sys.stderr)
        for field in ("replan_period_s", "min_clearance_m"):  # budget_s: the class checks it
            v = getattr(engine.planner, field)
            if not _bg_value_ok(field, v):
                raise UserError(f"{path}: planner.{field} {v}: need {_BG_NEEDS[field]}")
    given = {f: getattr(args, a) for _, a, f in _BG_FLAGS if getattr(args, a) is not None}
    return replace(engine.planner, **given)


def _serve_limits(args: argparse.Namespace):
    """The API's input limits (wm.limits) from ``wm serve``'s options."""
    from wm.limits import ServeLimits

    if args.rate_limit is not None and not args.rate_limit > 0:
        raise UserError(f"--rate-limit {args.rate_limit}: need requests a second > 0")
    if args.burst < 1:
        raise UserError(f"--burst {args.burst}: need at least 1")
    if args.queue < 1:
        raise UserError(f"--queue {args.queue}: need at least 1 frame")
    return ServeLimits(rate_per_s=args.rate_limit, burst=args.burst)


def cmd_whatis(args: argparse.Namespace) -> int:
    """What Is over a KD file: the self state and one entity (world frame), as of a time, in
    one run of the file (``--run``; default the newest)."""
    import kd_store
    from wm.whatis import WhatIs

    path = Path(args.kd)
    if not path.exists():
        raise FileNotFoundError(f"KD file {path} does not exist")
    run = "latest" if args.run is None else args.run
    with kd_store.open(path, read_only=True, run=run) as kd:
        selves = [f.id for f in kd.entities() if f.name == "self"]
        wi = WhatIs(kd, self_id=selves[0] if selves else None)
        ids = [args.entity] if args.entity is not None else selves
        if not ids:
            raise UserError(f"{path}: no self entity; give --entity ID")
        for i in ids:
            a = wi.entity(i, args.t_ns)
            print(
                f"entity {a.entity_id} ({a.class_name}, {a.status}, conf {a.confidence:.2f}) "
                f"at t_ns={a.t_ns} [{a.source}] in {a.frame}: position "
                f"{np.round(a.position, 3).tolist()} m, "
                f"velocity {np.round(a.velocity, 3).tolist()} m/s"
            )
    return 0


def _parse_waypoints(text: str) -> tuple[np.ndarray, np.ndarray]:
    try:
        rows = [[float(v) for v in part.split(",")] for part in text.split(";") if part.strip()]
        arr = np.array(rows, dtype=np.float64)
    except ValueError as e:
        raise UserError(f"--waypoints {text!r}: expected 't,x,y;t,x,y;...' ({e})") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise UserError(f"--waypoints {text!r}: each waypoint needs t,x,y")
    return arr[:, 0], arr[:, 1:]


def _check_stored_kd(path_text: str) -> Path:
    """The KD file an earlier ``wm run`` wrote, or one clear error if it is missing."""
    path = Path(path_text)
    if path_text == ":memory:" or not path.exists():
        raise FileNotFoundError(f"KD file {path} does not exist")
    return path


def _open_stored_kd(path_text: str, config: KDConfig | None = None):
    """A KD file an earlier ``wm run`` wrote, opened read-only with ``config`` (the ``kd``
    section of the run's configuration; None: the defaults)."""
    import kd_store

    return kd_store.open(_check_stored_kd(path_text), config, read_only=True)


def _no_log_options(args: argparse.Namespace, command: str) -> None:
    """Refuse log-only options in the stored-KD form (they would be silently ignored)."""
    if args.seconds is not None:
        raise UserError(f"wm {command} --kd {args.kd}: --seconds applies to a log; give LOG")


def cmd_whatif(args: argparse.Namespace) -> int:
    """What If about one waypoint plan (body-frame waypoints relative to the vehicle's last
    pose), judged by VJ. With LOG: run the log (its first --seconds), then ask the live node.
    Without LOG: ask over the maps and entities a run stored in --kd (tiles, last states)."""
    t_s, xy_body = _parse_waypoints(args.waypoints)
    if args.log is not None:
        from wm.run import run_node

        log = _check_log(args.log)
        config = _engine_config(args, args.kd)  # a KD file that exists: its recorded one
        node = run_node(log, args.kd, config, seconds=args.seconds)
        try:
            _record_config(args.kd, config)  # for `wm whatif --kd` and `wm render --kd` later
            lines = whatif_lines(
                node.kd, node.stack, node.self_id, node.stack.T_world_body, t_s, xy_body,
                args.level, config,
            )  # fmt: skip
        finally:
            node.kd.close()
    else:
        from wm.tiles import TileError, stored_maps

        if args.kd == ":memory:":
            raise UserError("whatif needs a LOG, or --kd KD.duckdb written by `wm run`")
        _no_log_options(args, "whatif")
        _check_stored_kd(args.kd)  # a missing KD is the error, before its configuration's
        config = _engine_config(args, args.kd)
        with _open_stored_kd(args.kd, config.kd) as kd:
            # the maps' geometry (levels, resolutions, sizes) must be the run's
            maps = stored_maps(kd, config.maps)
            known = [lvl.name for lvl in maps.stack.levels]
            if args.level in known and args.level not in maps.levels:
                raise TileError(
                    f"KD {args.kd} holds no map tiles of level {args.level!r}; "
                    f"levels with tiles: {maps.levels}"
                )
            lines = whatif_lines(
                kd, maps.stack, maps.self_id, maps.T_world_body, t_s, xy_body, args.level, config
            )
    print("\n".join(lines))
    return 0


def whatif_lines(
    kd, stack, self_id: int, T_world_body: np.ndarray, t_s: np.ndarray, xy_body: np.ndarray,
    level: str, config: EngineConfig | None = None,
) -> list[str]:  # fmt: skip
    """Simulate the plan ``t_s`` (K,) s, ``xy_body`` (K, 2) m in the body frame of
    ``T_world_body`` over ``stack`` and ``kd`` at ``level``, rolled out as ``config`` (an
    EngineConfig; None: the defaults) says (its ``whatif`` section, ``node.vehicle`` and
    ``kd.memory.horizons_s``) and judged with its ``node.vj``; the lines a user reads."""
    from core.geometry import transform_points
    from wm import vj
    from wm.engine_config import EngineConfig
    from wm.whatif import WaypointPlan, WhatIf

    engine = config if config is not None else EngineConfig()
    xy = transform_points(T_world_body, np.column_stack([xy_body, np.zeros(len(xy_body))]))[:, :2]
    wi = WhatIf(kd, stack, engine, self_id=self_id)
    res = wi.simulate([WaypointPlan(t_s, xy, "cli")], level=level)
    ev = vj.evaluate(res, xy[-1], engine.node.vj)
    hit = int(res.collision_entity[0])
    when = f"entity {hit} at {res.collision_t_s[0]:.1f} s" if hit >= 0 else "none"
    return [
        f"plan over {res.t_s[-1]:.1f} s at level {level}: {res.distance_m[0]:.1f} m",
        f"first collision: {when}",
        f"least clearance {res.min_clearance_m[0]:.2f} m; limited steps {res.limited_steps[0]}",
        f"VJ: cost {ev.cost[0]:.2f}, risk {ev.risk[0]:.2f}, benefit {ev.benefit[0]:.2f}",
    ]


def cmd_render(args: argparse.Namespace) -> int:
    """Pictures of every map level: ``LOG --out DIR`` runs the log (or its first --seconds);
    ``--kd KD OUT_DIR`` draws the maps and entities a run stored in the KD, without the log."""
    paths_in = list(args.paths)
    if args.kd is not None:
        _no_log_options(args, "render")
        if len(paths_in) + (args.out is not None) != 1:
            raise UserError(
                f"render --kd {args.kd}: give one output folder (OUT_DIR or --out), no LOG; "
                f"got {paths_in + ([args.out] if args.out else [])}"
            )
        from wm.render import render_maps
        from wm.tiles import stored_maps

        out = Path(args.out or paths_in[0])
        _check_stored_kd(args.kd)  # a missing KD is the error, before its configuration's
        config = _engine_config(args, args.kd)
        with _open_stored_kd(args.kd, config.kd) as kd:
            # the maps' geometry (levels, resolutions, sizes) must be the run's
            maps = stored_maps(kd, config.maps)
            paths = render_maps(kd, maps.stack, maps.self_id, out, maps.levels)
        for lvl in maps.stack.levels:
            if lvl.name not in maps.levels:
                print(f"note: {args.kd} holds no tiles of level {lvl.name!r}; not drawn")
    else:
        if args.out is None and len(paths_in) == 2:
            paths_in, args.out = paths_in[:1], paths_in[1]
        if len(paths_in) != 1 or args.out is None:
            raise UserError(
                f"render: give LOG --out DIR, or --kd KD.duckdb OUT_DIR; got {paths_in}"
            )
        from wm.render import render_run
        from wm.run import run_node

        node = run_node(_check_log(paths_in[0]), ":memory:", _engine_config(args), args.seconds)
        try:
            paths = render_run(node, Path(args.out))
        finally:
            node.kd.close()
    for p in paths:
        print(f"picture {p}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    """The scores of one KD against one log's ground truth (docs/evaluation.md)."""
    import json

    from wm.evaluation import evaluate_files

    scores = evaluate_files(_check_log(args.log), args.kd)
    for name, value in scores.items():
        print(f"{name}: {value:.4g}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(scores, indent=2) + "\n")
        print(f"scores {args.json}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """The main job on the embedded default: simulate the default scenario, then run it."""
    out = Path(args.out) / "default.mcap"
    print(f"simulating the default scenario ({args.seconds or 'full'} s) into {out}")
    rc = cmd_simulate(
        argparse.Namespace(
            scenario="default", out=out, seconds=args.seconds, seed=None, no_progress=False
        )
    )
    if rc:
        return rc
    print()
    kd = Path(args.out) / "default.duckdb"
    rc = cmd_run(
        argparse.Namespace(
            log=str(out), kd=str(kd), report=str(Path(args.out) / "report.json"),
            render=str(Path(args.out) / "pictures"), poses=args.poses, config=args.config,
            no_progress=False, seconds=None, overwrite=True,  # the demo's own KD of an earlier demo
        )
    )  # fmt: skip
    print(f"\nKD: {kd} (try: wm query {kd} \"SELECT class_name, status, count(*) FROM entities"
          f" GROUP BY ALL\")")  # fmt: skip
    print(f"pictures: {Path(args.out) / 'pictures'}; report: {Path(args.out) / 'report.json'}")
    return rc


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="wm", description="4D/RCS world model and perception engine")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="simulate a scenario into an MCAP log (ROS 2 messages)")
    s.add_argument("scenario", help="scenario name (default, village, open) or a YAML file")
    s.add_argument("--out", required=True, help="output log path, *.mcap")
    s.add_argument("--seconds", type=float, default=None, help="duration (default: scenario's)")
    s.add_argument("--seed", type=int, default=None, help="random seed (default: scenario's)")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_simulate)

    i = sub.add_parser("log-info", help="topics, types, counts, duration and rates of a log")
    i.add_argument("log", help="MCAP, ROS 1 bag, ROS 2 bag folder, KITTI/7-Scenes/AV2 folder")
    i.add_argument("--skip-corrupt", action="store_true", help="skip and count corrupt records")
    i.add_argument(
        "--check", action="store_true", help="decode every frame and report what had to be dropped"
    )
    i.set_defaults(func=cmd_log_info)

    q = sub.add_parser("query", help="read-only SQL over a KD file (views: see README)")
    q.add_argument("kd", help="KD file (DuckDB)")
    q.add_argument("sql", help="one SELECT over the views (entities, events, ...)")
    q.add_argument("--show-rows", type=int, default=50, help="rows to print (default 50)")
    q.add_argument(
        "--max-rows", type=int, default=1_000_000,
        help="refuse a result of more rows than this (default 1000000)",
    )  # fmt: skip
    q.add_argument(
        "--max-mb", type=float, default=256.0,
        help="refuse a result larger than this many MB of Arrow data (default 256)",
    )  # fmt: skip
    q.add_argument("--parquet", default=None, help="write the result to this new .parquet file")
    q.add_argument(
        "--overwrite", action="store_true", help="let --parquet replace a file that exists"
    )
    q.add_argument(
        "--timeout", type=float, default=30.0, help="seconds before the query is stopped"
    )
    q.add_argument("--memory-limit", default="1GB", help="DuckDB memory limit (default 1GB)")
    q.set_defaults(func=cmd_query)

    def config_flags(sp: argparse.ArgumentParser) -> None:
        sp.add_argument(
            "--poses", choices=("odometry", "truth"), default=None,
            help="vehicle poses from LADAR+wheel odometry (default) or the log's ground truth "
            "(node.pose_source)",
        )  # fmt: skip
        sp.add_argument(
            "--config", default=None, metavar="FILE.yaml",
            help="engine configuration: the fields it gives change the defaults (wm config "
            "--default prints them all); flags given override it",
        )  # fmt: skip

    def snapshot_flags(sp: argparse.ArgumentParser) -> None:
        sp.add_argument(
            "--snapshot", default=None, metavar="S",
            help="publish a read-only copy of the KD here, for other processes to open while "
            "the node writes (docs/kd.md); an existing S only if it is an earlier snapshot",
        )  # fmt: skip
        sp.add_argument(
            "--snapshot-every", type=float, default=None, metavar="SECONDS",
            help="publish the snapshot at most this often, in log seconds (default 5), and at "
            "the end",
        )  # fmt: skip

    r = sub.add_parser("run", help="the main job: a log through the world model into a KD")
    r.add_argument("log", help="any supported log (see log-info)")
    r.add_argument("--kd", required=True, help="KD file to write (DuckDB); must not exist")
    r.add_argument("--overwrite", action="store_true", help="replace the --kd file if it exists")
    r.add_argument(
        "--append",
        action="store_true",
        help="add this run to an existing --kd file (each run has its run_id in every view)",
    )
    r.add_argument("--report", default=None, help="write the summary as JSON here")
    r.add_argument("--render", default=None, help="write pictures of every map level here")
    r.add_argument("--seconds", type=float, default=None, help="only the first S seconds")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.add_argument(
        "--decode-in-process", action="store_true",
        help="decode the log in the node's process (default: ahead, in a child process)",
    )  # fmt: skip
    r.add_argument(
        "--skip-corrupt", action="store_true",
        help="skip corrupt or duplicated log records (counted in the report) instead of stopping",
    )  # fmt: skip
    config_flags(r)
    snapshot_flags(r)
    r.set_defaults(func=cmd_run)

    k = sub.add_parser("config", help="print the engine configuration as YAML (--default)")
    k.add_argument("file", nargs="?", default=None, help="a configuration file to check and show")
    k.add_argument("--default", action="store_true", help="the defaults: a file to start from")
    k.set_defaults(func=cmd_config)

    c = sub.add_parser("check", help="integrity of a KD file: every row points at a frame")
    c.add_argument("kd", help="KD file (DuckDB), opened read-only")
    c.set_defaults(func=cmd_check)

    w = sub.add_parser("whatis", help="What Is over a KD file: self state or an entity")
    w.add_argument("kd", help="KD file (DuckDB)")
    w.add_argument("--entity", type=int, default=None, help="entity id (default: self)")
    w.add_argument("--t-ns", type=int, default=None, help="as of this time (ns)")
    w.add_argument(
        "--run", type=int, default=None, help="which run of the KD (default: the newest)"
    )
    w.set_defaults(func=cmd_whatis)

    f = sub.add_parser(
        "whatif", help="simulate a waypoint plan from the end of a log, or of a run stored in a KD"
    )
    f.add_argument("log", nargs="?", default=None, help="any supported log (omit: use --kd alone)")
    f.add_argument(
        "--kd", default=":memory:",
        help="with LOG: the KD to write (default: in memory); without: a KD `wm run` wrote",
    )  # fmt: skip
    f.add_argument("--waypoints", required=True, help="'t,x,y;...' seconds, body-frame metres")
    f.add_argument("--level", default="subsystem", help="map level (default subsystem)")
    f.add_argument("--seconds", type=float, default=None, help="only the first S seconds")
    config_flags(f)
    f.set_defaults(func=cmd_whatif)

    g = sub.add_parser(
        "render", help="pictures of every map level: of a log's run, or of a run stored in a KD"
    )
    g.add_argument(
        "paths", nargs="*", metavar="LOG | OUT_DIR",
        help="LOG (with --out DIR), or OUT_DIR with --kd",
    )  # fmt: skip
    g.add_argument("--out", default=None, help="folder for the PNG files")
    g.add_argument("--kd", default=None, help="draw the maps a run stored in this KD file")
    g.add_argument("--seconds", type=float, default=None, help="only the first S seconds")
    config_flags(g)
    g.set_defaults(func=cmd_render)

    e = sub.add_parser("evaluate", help="scores of a KD against a log's ground truth")
    e.add_argument("log", help="the log the KD was made from (with ground truth)")
    e.add_argument("kd", help="KD file `wm run` wrote (DuckDB)")
    e.add_argument("--json", default=None, help="write the scores as JSON here")
    e.set_defaults(func=cmd_evaluate)

    v = sub.add_parser("serve", help="a live node replaying a log, What Is over HTTP (/v1)")
    source = v.add_mutually_exclusive_group(required=True)
    source.add_argument("--replay", help="any supported log, fed at its own pace")
    source.add_argument(
        "--ingest", action="store_true",
        help="no log: clients POST ROS 2 messages (CDR) to /v1/ingest (wm.ingest)",
    )  # fmt: skip
    v.add_argument("--queue", type=int, default=64, help="--ingest: frames waiting at most")
    v.add_argument(
        "--rate-limit", type=float, default=None,
        help="requests a second each client address may make (default: no limit); 429 beyond",
    )  # fmt: skip
    v.add_argument("--burst", type=int, default=100, help="requests at once under --rate-limit")
    v.add_argument("--rate", type=float, default=1.0, help="replay speed (0: as fast as it can)")
    v.add_argument(
        "--in-process", action="store_true",
        help="run the node in a thread of the server's process (default: a process of its own)",
    )  # fmt: skip
    v.add_argument("--kd", default="live.duckdb", help="KD file the node writes (DuckDB)")
    v.add_argument("--host", default="127.0.0.1", help="address to bind (default: localhost)")
    v.add_argument("--port", type=int, default=8765)
    v.add_argument(
        "--token-env", default=None,
        help="name of an environment variable holding a bearer token every request must carry",
    )  # fmt: skip
    config_flags(v)
    snapshot_flags(v)
    v.set_defaults(func=cmd_serve)

    b = sub.add_parser(
        "bg", help="a behavior-generation planner in its own process, over a live node's API"
    )
    b.add_argument("--url", required=True, help="the node's address, e.g. http://127.0.0.1:8765")
    b.add_argument(
        "--goal", required=True,
        help="'x,y': the goal in the node's world frame, m (a negative x as --goal=-5,3)",
    )  # fmt: skip
    b.add_argument(
        "--token-env", default=None,
        help="name of an environment variable holding the server's bearer token",
    )  # fmt: skip
    b.add_argument(
        "--period-s", type=float, default=None,
        help="replan every S seconds of log time, at the first new cycle after (default: "
        "the configuration's planner.replan_period_s, 0.5)",
    )  # fmt: skip
    b.add_argument("--cycles", type=int, default=None, help="stop after N plans (default: "
                   "when the node's log has ended)")  # fmt: skip
    b.add_argument(
        "--budget-s", type=float, default=None,
        help="wall seconds a planning cycle may take before no further batch of plans is sent "
        "(default: planner.budget_s if the --config file gives it, else 1: each batch is a "
        "request that waits for the node's cycle in progress)",
    )  # fmt: skip
    b.add_argument(
        "--min-clearance-m", type=float, default=None,
        help="plans passing closer than this (m) to a perceived object are unsafe (default: "
        "the configuration's planner.min_clearance_m, 0.5); more leaves room for objects "
        "perception sees smaller than they are",
    )  # fmt: skip
    b.add_argument(
        "--level", default=None,
        help="map level (default: the configuration's planner.level, subsystem)",
    )  # fmt: skip
    b.add_argument(
        "--config", default=None, metavar="FILE.yaml",
        help="engine configuration: its planner section (wm config --default prints it); "
        "flags given override it",
    )  # fmt: skip
    b.add_argument("--json", action="store_true", help="one JSON object a plan, path included")
    b.add_argument("--no-tell", action="store_true", help="do not tell the node the plan")
    b.set_defaults(func=cmd_bg)

    d = sub.add_parser("demo", help="simulate the default scenario and run the world model on it")
    d.add_argument("--out", default="out", help="folder for the demo's files (default: out/)")
    d.add_argument("--seconds", type=float, default=None, help="duration (default: scenario's)")
    config_flags(d)
    d.set_defaults(func=cmd_demo)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("wm: interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        if args.debug or not isinstance(e, _user_error_types()):
            raise
        print(f"wm {args.command}: error: {e}", file=sys.stderr)
        return EXIT_USER_ERROR


if __name__ == "__main__":
    sys.exit(main())
