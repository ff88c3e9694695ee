"""The multi-seed evaluation sweep (docs/evaluation.md): per (scenario, seed), simulate a log
(cached), run ``wm run`` on it in a fresh process, score the KD with ``wm evaluate``, then
print a per-scenario table of the median and the worst seed of each figure and write one JSON
file per figure (bench/results.py ``record``).

    python -m wm.eval_sweep --scenarios default village open --seconds 20 --jobs 2 \\
        --out results/ [--n-seeds 2 | --seeds 1009 31337] [--engine-path /old/engine] \\
        [--poses truth] [--label NAME] [--cache out/eval-logs] [--work out/eval-runs]

Evaluation seeds (:data:`EVAL_SEEDS`) are never used for tuning; development seeds are each
scenario's own seed and 0..99 (:data:`DEV_SEEDS`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wm.evaluation import PHASES, EvalConfig, band_name, range_bands

REPO = Path(__file__).resolve().parents[1]
SCENARIO_DIR = REPO / "fixtures" / "scenarios"

#: Development (tuning) seeds: 0..99, plus each scenario's own seed (its YAML's ``seed``).
DEV_SEEDS = range(100)
#: Evaluation seeds, the same 8 for every scenario, spread over 1e3..1e6; never used for tuning.
EVAL_SEEDS: tuple[int, ...] = (1_009, 31_337, 77_101, 142_857, 271_828, 404_713, 618_034, 999_983)


@dataclass(frozen=True)
class Figure:
    """One reported figure: its key in the scores, unit, whether higher is better, and its
    target on the median and on the worst seed (None: reported without a target)."""

    key: str
    unit: str
    higher_better: bool
    target: float | None = None
    worst_target: float | None = None

    def target_text(self) -> str | None:
        if self.target is None:
            return None
        op = ">=" if self.higher_better else "<="
        text = f"median {op} {self.target:g}"
        if self.worst_target is not None:
            text += f", worst {op} {self.worst_target:g}"
        return text

    def meets(self, value: float, target: float | None) -> bool | None:
        if target is None or not math.isfinite(value):
            return None
        return value >= target if self.higher_better else value <= target


FIGURES: tuple[Figure, ...] = (
    Figure("mota", "ratio", True, 0.8, 0.6),
    Figure("motp", "m", False),
    Figure("idf1", "ratio", True),
    Figure("hota", "ratio", True),
    Figure("precision", "ratio", True, 0.9),
    Figure("recall", "ratio", True),
    Figure("num_switches", "count", False),
    Figure("switches_per_100", "per 100 track-frames", False, 1.0),
    Figure("num_fragmentations", "count", False),
    Figure("classification_accuracy", "ratio", True, 0.85),
    Figure("static_speed_median_mps", "m/s", False, 0.2),
    Figure("static_speed_mean_mps", "m/s", False),
    Figure("person_count_error", "persons", False),
    Figure("ape_rmse_m", "m", False),
    Figure("rpe_pct", "%", False),
    Figure("drift_pct", "%", False, 1.0, 1.5),
)


def scenarios_available() -> list[str]:
    """The scenario names in fixtures/scenarios (every YAML file there)."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


def scenario_seed(name: str) -> int | None:
    """The scenario's own seed (a development seed), or None."""
    import yaml

    path = SCENARIO_DIR / f"{name}.yaml"
    if not path.exists():
        return None
    seed = (yaml.safe_load(path.read_text()) or {}).get("seed")
    return None if seed is None else int(seed)


def check_eval_seeds(scenarios: Sequence[str], seeds: Sequence[int]) -> None:
    """Refuse a development seed among the evaluation seeds (the split in the docs)."""
    for name in scenarios:
        dev = set(DEV_SEEDS) | {scenario_seed(name)}
        clash = sorted(set(seeds) & dev)
        if clash:
            raise SystemExit(f"seeds {clash} are development seeds of scenario {name!r}")


def _run(cmd: list[str], cwd: Path, env: dict[str, str], timeout_s: float, log: Path) -> None:
    """Run ``cmd``; its output goes to ``log``. Raises RuntimeError naming the log on failure."""
    with log.open("w") as out:
        out.write("$ " + shlex.join(cmd) + "\n")
        out.flush()
        rc = subprocess.run(
            cmd, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT, timeout=timeout_s
        ).returncode
    if rc != 0:
        raise RuntimeError(f"{shlex.join(cmd)} exited with {rc}; see {log}")


def simulate_cached(
    scenario: str, seed: int, seconds: float, cache: Path, timeout_s: float
) -> Path:
    """The cached log of (scenario, seed, seconds), simulated by this tree when missing or
    when it predates the per-object return counts the scorer reads (:func:`counts_returns`).
    Its name carries the simulator's version (``fixtures.SIMULATOR_VERSION``), so a log an
    older simulator wrote is never taken for this one's."""
    from fixtures import SIMULATOR_VERSION

    log = cache / f"{scenario}-seed{seed}-{seconds:g}s-sim{SIMULATOR_VERSION}.mcap"
    if log.exists() and counts_returns(log):
        return log
    cache.mkdir(parents=True, exist_ok=True)
    tmp = log.with_suffix(".mcap.tmp.mcap")
    cmd = [
        sys.executable, "-m", "wm.cli", "simulate", scenario, "--out", str(tmp),
        "--seconds", f"{seconds:g}", "--seed", str(seed), "--no-progress",
    ]  # fmt: skip
    _run(cmd, REPO, dict(os.environ), timeout_s, log.with_suffix(".simulate.txt"))
    tmp.rename(log)
    return log


def counts_returns(log: Path) -> bool:
    """Whether the log's first truth boxes carry ``n_returns`` (simulated since 2026-12)."""
    from logs import open_log
    from logs.types import ObjectBoxes

    for boxes in open_log(log).frames(kinds=(ObjectBoxes,)):
        return boxes.n_returns is not None
    return False


def run_one(
    scenario: str, seed: int, args: argparse.Namespace, label: str
) -> dict[str, float] | str:
    """Simulate (cached), run and score one (scenario, seed): its scores, or why it failed."""
    work = Path(args.work).resolve() / label
    work.mkdir(parents=True, exist_ok=True)
    stem = work / f"{scenario}-seed{seed}"
    try:
        log = simulate_cached(
            scenario, seed, args.seconds, Path(args.cache).resolve(), args.timeout
        )
        kd = stem.with_suffix(".kd")
        for stale in (kd, Path(f"{kd}.wal")):
            stale.unlink(missing_ok=True)
        engine = Path(args.engine_path).resolve() if args.engine_path else REPO
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([str(engine), *filter(None, [env.get("PYTHONPATH")])])
        run_cmd = [
            sys.executable, "-m", "wm.cli", "run", str(log), "--kd", str(kd),
            "--report", str(stem.with_suffix(".report.json")), "--no-progress",
            "--poses", args.poses,
        ]  # fmt: skip
        t0 = time.perf_counter()
        # cwd = the engine, as `python -m` puts the working folder before PYTHONPATH
        _run(run_cmd, engine, env, args.timeout, stem.with_suffix(".run.txt"))
        run_s = time.perf_counter() - t0
        scores_path = stem.with_suffix(".scores.json")
        ev_cmd = [sys.executable, "-m", "wm.cli", "evaluate", str(log), str(kd)]
        _run(
            [*ev_cmd, "--json", str(scores_path)], REPO, dict(os.environ), args.timeout,
            stem.with_suffix(".evaluate.txt"),
        )  # fmt: skip
        scores = json.loads(scores_path.read_text())
        scores["run_wall_s"] = run_s
        return scores
    except (RuntimeError, subprocess.TimeoutExpired, OSError) as e:
        return f"{scenario} seed {seed}: {e}"


def summarize(values: list[float], fig: Figure) -> tuple[float, float, int]:
    """Median and worst seed over the finite values, and how many were finite."""
    v = np.array([x for x in values if math.isfinite(x)], dtype=np.float64)
    if not len(v):
        return math.nan, math.nan, 0
    worst = float(v.min() if fig.higher_better else v.max())
    return float(np.median(v)), worst, len(v)


def pooled(runs: list[dict[str, float]]) -> dict[str, float]:
    """Figures over all the seeds' frames together, as a benchmark of many sequences pools
    them: MOTA from the summed misses, false positives, switches and objects (a seed with two
    scored frames weighs two frames, where in the median it weighs as much as any), and the
    recall of each range band (``wm.evaluation.range_bands``) and of the log's start and the
    rest (``wm.evaluation.PHASES``) from its summed box-frames. Reported beside the medians,
    without targets."""
    out: dict[str, float] = {}
    n_obj = sum(r.get("num_objects", 0.0) for r in runs)
    errors = sum(
        r.get("num_misses", 0.0) + r.get("num_false_positives", 0.0) + r.get("num_switches", 0.0)
        for r in runs
    )
    out["mota_pooled"] = 1.0 - errors / n_obj if n_obj else math.nan
    for b in [band_name(lo, hi) for lo, hi in range_bands(EvalConfig())] + list(PHASES):
        n = sum(r.get(f"box_frames_{b}", 0.0) for r in runs)
        hit = sum(r[f"recall_{b}"] * r[f"box_frames_{b}"] for r in runs if r.get(f"box_frames_{b}"))
        out[f"recall_{b}_pooled"] = hit / n if n else math.nan
        out[f"box_frames_{b}_pooled"] = n
    return out


def table(scenario: str, runs: list[dict[str, float]], label: str) -> str:
    """The per-scenario table: median, worst seed and target of each figure."""
    lines = [
        f"{scenario} [{label}]: {len(runs)} seeds",
        f"  {'figure':26s} {'median':>9s} {'worst':>9s} {'n':>3s}  target",
    ]
    for fig in FIGURES:
        med, worst, n = summarize([r.get(fig.key, math.nan) for r in runs], fig)
        ok = [fig.meets(med, fig.target), fig.meets(worst, fig.worst_target)]
        mark = "" if ok == [None, None] else ("  ok" if False not in ok else "  MISS")
        lines.append(
            f"  {fig.key:26s} {med:9.4g} {worst:9.4g} {n:3d}  {fig.target_text() or '-'}{mark}"
        )
    p = pooled(runs)
    lines.append(f"  pooled over the seeds: MOTA {p['mota_pooled']:.4g}; recall by box range")
    for lo, hi in range_bands(EvalConfig()):
        b = band_name(lo, hi)
        lines.append(
            f"    {lo:g}-{hi:g} m: {p[f'recall_{b}_pooled']:.4g} "
            f"of {p[f'box_frames_{b}_pooled']:.0f} box-frames"
        )
    lines.append(
        f"    first {EvalConfig().startup_s:g} s: {p['recall_startup_pooled']:.4g} of "
        f"{p['box_frames_startup_pooled']:.0f} box-frames; after: "
        f"{p['recall_steady_pooled']:.4g} of {p['box_frames_steady_pooled']:.0f}"
    )
    return "\n".join(lines)


def record_figures(
    scenario: str, runs: list[dict[str, float]], label: str, out: Path, command: str
) -> None:
    """One JSON file per figure (median) and per figure's worst seed, under ``out``."""
    import contextlib
    import io

    import bench.results as results

    results.RESULTS_DIR = out  # record() writes under this module global
    prefix = "eval" if label == "current" else f"eval-{label}"
    for fig in FIGURES:
        med, worst, n = summarize([r.get(fig.key, math.nan) for r in runs], fig)
        if not n:
            continue
        with contextlib.redirect_stdout(io.StringIO()):  # the table already shows them
            _record_pair(results, f"{prefix}_{scenario}_{fig.key}", fig, med, worst, command)
    with contextlib.redirect_stdout(io.StringIO()):
        for key, value in pooled(runs).items():
            if key.startswith("box_frames") or not math.isfinite(value):
                continue
            results.record(f"{prefix}_{scenario}_{key}", value, "ratio", command=command)


def _record_pair(results, name: str, fig: Figure, med: float, worst: float, command: str) -> None:
    """The median and worst-seed records of one figure."""
    worst_target = fig.target_text()
    if fig.worst_target is not None:
        worst_target = f"worst {'>=' if fig.higher_better else '<='} {fig.worst_target:g}"
    results.record(f"{name}_median", med, fig.unit, target=fig.target_text(), command=command)
    results.record(f"{name}_worst", worst, fig.unit, target=worst_target, command=command)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m wm.eval_sweep", description=__doc__.split("\n")[0])
    p.add_argument("--scenarios", nargs="*", default=None, help="default: every fixtures YAML")
    p.add_argument("--seeds", nargs="*", type=int, default=None, help="default: EVAL_SEEDS")
    p.add_argument("--n-seeds", type=int, default=None, help="only the first N seeds")
    p.add_argument("--seconds", type=float, default=20.0, help="log length (default 20 s)")
    p.add_argument("--jobs", type=int, default=2, help="(scenario, seed) runs side by side")
    p.add_argument("--out", default=str(REPO / "results"), help="folder for the JSON figures")
    p.add_argument("--cache", default=str(REPO / "out" / "eval-logs"), help="simulated logs")
    p.add_argument("--work", default=str(REPO / "out" / "eval-runs"), help="KDs and scores")
    p.add_argument("--engine-path", default=None, help="run this engine copy (PYTHONPATH first)")
    p.add_argument("--poses", choices=("odometry", "truth"), default="odometry")
    p.add_argument("--label", default=None, help="name of this run in tables and JSON names")
    p.add_argument(
        "--development", action="store_true",
        help="score development seeds (0..99, given with --seeds) while tuning; labelled dev-",
    )  # fmt: skip
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds per subprocess")
    return p


def sweep(argv: Sequence[str] | None = None) -> dict[str, list[dict[str, float] | str]]:
    """Run the sweep; returns scenario -> per-seed scores (or failure texts)."""
    args = build_parser().parse_args(argv)
    scenarios = args.scenarios or scenarios_available()
    seeds = list(args.seeds if args.seeds else EVAL_SEEDS)[: args.n_seeds]
    if args.development:
        if not set(seeds) <= set(DEV_SEEDS):
            raise SystemExit(f"--development takes seeds in 0..99 only, got {seeds}")
    else:
        check_eval_seeds(scenarios, seeds)
    label = args.label or (
        "engine-" + Path(args.engine_path).name if args.engine_path else "current"
    )
    if args.development:
        label = "dev-" + label
    if args.poses == "truth":
        label += "-poses-truth"
    command = "python -m wm.eval_sweep " + shlex.join(sys.argv[1:] if argv is None else argv)
    pairs = [(s, n) for s in scenarios for n in seeds]
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        done = list(pool.map(lambda sn: run_one(sn[0], sn[1], args, label), pairs))
    by: dict[str, list[dict[str, float] | str]] = {s: [] for s in scenarios}
    for (s, _), r in zip(pairs, done, strict=True):
        by[s].append(r)
    for s, rs in by.items():
        runs = [r for r in rs if isinstance(r, dict)]
        for r in rs:
            if isinstance(r, str):
                print(f"FAILED {r}")
        print(table(s, runs, label))
        if runs:
            record_figures(s, runs, label, Path(args.out), command)
    print(f"{len(pairs)} runs in {time.perf_counter() - t0:.0f} s wall")
    return by


def main(argv: Sequence[str] | None = None) -> int:
    by = sweep(argv)
    return 0 if all(isinstance(r, dict) for rs in by.values() for r in rs) else 1


if __name__ == "__main__":
    sys.exit(main())
