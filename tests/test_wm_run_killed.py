"""A killed `wm run` leaves nothing running: its odometry process notices that the node's
process is gone and exits (and with it the last holder of the decoder's pipe, so the decoder
exits too). And it keeps what it saw: the KD file holds the entities of the run up to the
last flush (every second of log time)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _children(pid: int) -> set[int]:
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out |= {int(c) for c in (task / "children").read_text().split()}
        except OSError:
            pass
    return out


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("killed") / "k.mcap"
    return simulate_to_log("default", path, seconds=8.0, seed=45, progress=False)


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
def test_sigkill_of_wm_run_leaves_no_process_and_keeps_what_it_saw(
    log: Path, tmp_path: Path
) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "-m", "wm.cli", "run", str(log), "--kd", str(tmp_path / "k.kd"),
           "--no-progress"]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        kids: set[int] = set()
        deadline = time.monotonic() + 60
        while len(kids) < 2 and time.monotonic() < deadline and proc.poll() is None:
            kids |= _children(proc.pid)  # the decoder and the odometry process
            time.sleep(0.05)
        assert len(kids) >= 2, "wm run started no odometry and decoder processes"
        time.sleep(4.0)  # a few seconds of the 8 s log
        assert proc.poll() is None, "the run ended before it could be killed"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        deadline = time.monotonic() + 10
        while any(_running(k) for k in kids) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [k for k in kids if _running(k)]
        import kd_store

        with kd_store.open(tmp_path / "k.kd", read_only=True) as kd:
            n = kd.sql(
                "SELECT count(*) AS n FROM entities WHERE level = 4 AND status = 'confirmed'"
            ).to_pylist()[0]["n"]
            states = kd.sql("SELECT count(*) AS n FROM entity_states").to_pylist()[0]["n"]
        assert n >= 3 and states >= 50  # objects confirmed in the first seconds, with states
    finally:
        if proc.poll() is None:
            proc.kill()
