"""A killed `wm run` leaves nothing running: the kernel kills its children, the log decoder
and the odometry process, when their parent dies (core.process.die_with_parent), within 2 s of
the SIGKILL. And it keeps what it saw: the KD file holds the entities of the run up to the
last flush (every second of log time)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from wm.campaign import _running
from wm.campaign import children as _children
from wm.campaign import kind_of as _kind

REPO = Path(__file__).resolve().parents[1]


KILL_AT_CPU_S = 5.0


def _cpu_s(pid: int) -> float:
    """User plus system CPU seconds the process ``pid`` has used (0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("killed") / "k.mcap"
    return simulate_to_log("default", path, seconds=16.0, seed=45, progress=False)


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
        kids: dict[int, str] = {}
        deadline = time.monotonic() + 60
        while len(set(kids.values())) < 2 and time.monotonic() < deadline and proc.poll() is None:
            # every poll reads every child's command line again: a child caught between its
            # fork and its exec still shows the parent's, so the decoder looks like odometry
            kids |= {k: _kind(k) for k in _children(proc.pid)}
            time.sleep(0.05)
        assert {"decoder", "odometry"} <= set(kids.values()), f"children seen: {kids}"
        # a few seconds into the 16 s log, by the run's own CPU time (a whole run of its first
        # 8 s took 5-10 s of it, depending on the machine: the kill then came as often after
        # the end as before it), so that a loaded machine does not kill it before it got
        # anywhere and a fast one not after it is done
        while _cpu_s(proc.pid) < KILL_AT_CPU_S and proc.poll() is None:
            time.sleep(0.05)
        assert proc.poll() is None, "the run ended before it could be killed"
        killed = time.monotonic()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        while any(_running(k) for k in kids) and time.monotonic() < killed + 2.0:
            time.sleep(0.02)
        left = {k: kind for k, kind in kids.items() if _running(k)}
        assert not left, f"children still running 2 s after the SIGKILL: {left}"
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
