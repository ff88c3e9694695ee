"""Run every benchmark module ``bench/bench_*.py`` (its ``main()``), or those named on the
command line: ``python -m bench [kd maps ...]``. Figures land in ``results/*.json``.

Each module runs in a fresh Python process, so a figure does not depend on which benchmarks
ran before it in the same run (a process that has built simulated worlds, KD files and maps
carries a larger heap, and Python-heavy code pays for it in longer garbage collections).
Within a module, a figure and its baseline still run side by side in one process.

The processes run with glibc's allocator held in its steady state (``MALLOC_MMAP_THRESHOLD_``,
``MALLOC_TRIM_THRESHOLD_``; a value already in the environment wins). Left to itself, a fresh
process maps and unmaps every buffer above 128 KiB, so a baseline that allocates one on every
call (``np.bincount(..., minlength=65536)``, ``cv2.phaseCorrelate``) pays page faults it does
not pay in a long-running process: measured here 2-2.5x slower (bincount 190 against 580
Mpoints/s, phaseCorrelate 0.83 against 0.48 ms), which made our ratios look better than they
are. Held steady, every figure compares against the baseline at its best.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

STEADY_ALLOCATOR = {
    "MALLOC_MMAP_THRESHOLD_": str(32 << 20),  # buffers below 32 MiB come from the heap
    "MALLOC_TRIM_THRESHOLD_": str(64 << 20),  # and freed memory stays there for the next
}


def main(argv: list[str]) -> int:
    here = Path(__file__).resolve().parent
    names = sorted(p.stem for p in here.glob("bench_*.py"))
    if argv:
        names = [n for n in names if any(a in n for a in argv)]
    env = {**STEADY_ALLOCATOR, **os.environ}
    failed = []
    for name in names:
        print(f"== {name}", flush=True)
        code = f"import bench.{name} as m; m.main()"
        if subprocess.run([sys.executable, "-c", code], cwd=here.parent, env=env).returncode != 0:
            failed.append(name)
    if failed:
        print(f"benchmarks that failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
