"""The ``wm`` command line.

    wm simulate SCENARIO --out LOG.mcap [--seconds S] [--seed N]
    wm log-info LOG [--skip-corrupt] [--check]
    wm query KD.duckdb "SELECT ..." [--parquet OUT]
    wm demo [--out DIR]

Errors a user can cause (an unknown scenario, a corrupt log, a missing file) are printed as one
clear line on stderr with exit status 2; ``--debug`` shows the traceback as well.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

EXIT_USER_ERROR = 2


class UserError(Exception):
    """A problem with what the user asked for; printed without a traceback."""


def _user_error_types() -> tuple[type[BaseException], ...]:
    """Exception types that describe bad input, each module's own (imported lazily)."""
    from kd_store.errors import KDError
    from maps.frames import GeometryError
    from sp.logs.types import LogError

    types: list[type[BaseException]] = [
        UserError,
        LogError,
        GeometryError,
        KDError,
        FileNotFoundError,
    ]
    try:
        from fixtures.scenario import ScenarioError
        from fixtures.sensors import SensorError

        types += [ScenarioError, SensorError]
    except ImportError:
        pass
    return tuple(types)


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
    from sp.logs import format_log_info, open_log

    path = Path(args.log)
    if not path.exists():
        raise FileNotFoundError(f"log {path} does not exist")
    source = open_log(path, skip_corrupt=args.skip_corrupt)
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
    import kd_store

    path = Path(args.kd)
    if not path.exists():
        raise FileNotFoundError(f"KD file {path} does not exist")
    with kd_store.open(path, read_only=True) as kd:
        table = kd.sql(args.sql)
    if args.parquet:
        import pyarrow.parquet as pq

        pq.write_table(table, args.parquet)
        print(f"wrote {table.num_rows} rows to {args.parquet}")
    else:
        print(format_table(table, args.max_rows))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """The main job on the embedded default: simulate the default scenario, then read it back."""
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
    return cmd_log_info(argparse.Namespace(log=out, skip_corrupt=False, check=True))


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
    q.add_argument("--max-rows", type=int, default=50, help="rows to print (default 50)")
    q.add_argument("--parquet", default=None, help="write the result to this Parquet file")
    q.set_defaults(func=cmd_query)

    d = sub.add_parser("demo", help="simulate the default scenario and show what the log holds")
    d.add_argument("--out", default="out", help="folder for the demo's files (default: out/)")
    d.add_argument("--seconds", type=float, default=None, help="duration (default: scenario's)")
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
