"""Run every benchmark module ``bench/bench_*.py`` (its ``main()``), or those named on the
command line: ``python -m bench [kd maps ...]``. Figures land in ``results/*.json``.

Each module runs in a fresh Python process, so a figure does not depend on which benchmarks
ran before it in the same run: a process that has built simulated worlds, KD files and maps
carries a larger heap (longer garbage collections for Python-heavy code) and a warmed
allocator (which favours baselines that allocate large buffers on every call). Within a
module, a figure and its baseline still run side by side in one process.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def main(argv: list[str]) -> int:
    here = Path(__file__).resolve().parent
    names = sorted(p.stem for p in here.glob("bench_*.py"))
    if argv:
        names = [n for n in names if any(a in n for a in argv)]
    failed = []
    for name in names:
        print(f"== {name}", flush=True)
        code = f"import bench.{name} as m; m.main()"
        if subprocess.run([sys.executable, "-c", code], cwd=here.parent).returncode != 0:
            failed.append(name)
    if failed:
        print(f"benchmarks that failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
