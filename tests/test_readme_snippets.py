"""The README's Python examples that run a world-model node work as written and lose nothing:
each runs in a fresh interpreter over a short simulated log, and the KD file it leaves holds
the confirmed objects and the vehicle's states up to the end of the log."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from node_runs import in_file

from logs import LadarScan, open_log

REPO = Path(__file__).resolve().parents[1]
SECONDS = 3.0


def node_snippets() -> list[str]:
    """The README's ```python blocks that use WorldModelNode, in order."""
    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)
    return [b for b in blocks if "WorldModelNode" in b]


def the_path(pattern: str, code: str) -> str:
    """The one string literal ``pattern`` captures in ``code``."""
    found = re.findall(pattern, code)
    assert len(found) == 1, f"expected one match of {pattern!r} in the snippet, got {found}"
    return found[0]


@pytest.fixture(scope="module")
def short_log(tmp_path_factory) -> Path:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("readme_log") / "default.mcap"
    return simulate_to_log("default", path, seconds=SECONDS, seed=42, progress=False)


def test_the_readme_has_a_node_example() -> None:
    assert node_snippets(), "README.md lost its Python example of WorldModelNode"


@pytest.mark.parametrize("k", range(len(node_snippets())))
def test_readme_node_snippet_runs_and_its_kd_file_is_complete(k, short_log, tmp_path) -> None:
    code = node_snippets()[k]
    log_in_code = the_path(r"open_log\(\"([^\"]+)\"\)", code)
    kd_in_code = the_path(r"kd_store\.open\(\"([^\"]+)\"\)", code)
    # as a reader would: the log where the snippet reads it, after `wm simulate --out` made
    # its folder (the only change to the snippet is the log's path)
    code = code.replace(f'"{log_in_code}"', repr(str(short_log)))
    (tmp_path / kd_in_code).parent.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
        timeout=600,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]

    last_sweep = max(f.t_ns for f in open_log(short_log).frames(kinds=(LadarScan,)))
    got = in_file(tmp_path / kd_in_code)
    assert got["objects"] >= 3
    assert got["self_states"] >= 0.8 * SECONDS * 10  # a self state per sweep (10 Hz)
    # the last sweeps are in the file too (the self state is at a sweep's middle)
    assert got["self_t_ns"] >= last_sweep - 150_000_000
