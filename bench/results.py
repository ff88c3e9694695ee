"""One JSON file per figure under ``results/``, the same shape for benchmarks and evaluations.

Each file holds ``{"name", "value", "unit", "baseline", "baseline_value", "ratio", "target",
"command"}`` so runs can be compared by anyone. ``ratio`` is ``value / baseline_value``.
"""

from __future__ import annotations

import json
import os
import re
import statistics
import time
from collections.abc import Callable
from pathlib import Path

RESULTS_DIR = Path(
    os.environ.get("WM_RESULTS_DIR", Path(__file__).resolve().parents[1] / "results")
)


def record(
    name: str,
    value: float,
    unit: str,
    *,
    baseline: str | None = None,
    baseline_value: float | None = None,
    target: str | None = None,
    command: str = "make bench",
) -> dict:
    """Write ``results/<name>.json`` and print one line; returns the record."""
    ratio = None
    if baseline_value not in (None, 0):
        ratio = float(value) / float(baseline_value)
    rec = {
        "name": name,
        "value": float(value),
        "unit": unit,
        "baseline": baseline,
        "baseline_value": None if baseline_value is None else float(baseline_value),
        "ratio": ratio,
        "target": target,
        "command": command,
    }
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", name)
    (RESULTS_DIR / f"{safe}.json").write_text(json.dumps(rec, indent=2) + "\n")
    extra = f"  vs {baseline} {baseline_value:.4g}  ratio {ratio:.3g}" if ratio is not None else ""
    print(f"{name}: {value:.4g} {unit}{extra}  (target: {target})", flush=True)
    return rec


def median_time(fn: Callable[[], object], repeat: int = 7, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` in seconds over ``repeat`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def median_times_interleaved(
    fns: dict[str, Callable[[], object]], repeat: int = 7, warmup: int = 1
) -> dict[str, float]:
    """Median wall time of each function, run interleaved so machine noise hits all alike."""
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    samples: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeat):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            samples[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in samples.items()}
