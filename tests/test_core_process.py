"""core.process.die_with_parent: a child that called it dies with its parent (Linux), and a
child whose parent died before the call exits at once."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}

# a middle process that starts a grandchild (which arms prctl, says so and sleeps), prints its
# pid, then sleeps until killed
MIDDLE = """
import os, subprocess, sys, time
child = (
    "import os, sys, time\\n"
    "from core.process import die_with_parent\\n"
    "print(os.getpid(), die_with_parent(int(sys.argv[1])), flush=True)\\n"
    "time.sleep(60)\\n"
)
p = subprocess.Popen([sys.executable, "-c", child, str(os.getpid())], stdout=sys.stdout)
time.sleep(60)
"""


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_child_dies_within_a_second_of_its_parents_sigkill() -> None:
    middle = subprocess.Popen(
        [sys.executable, "-c", MIDDLE], stdout=subprocess.PIPE, text=True, env=ENV, cwd=REPO
    )
    try:
        assert middle.stdout is not None
        pid, armed = middle.stdout.readline().split()
        assert armed == "True"
        assert _alive(int(pid))
        killed = time.monotonic()
        middle.send_signal(signal.SIGKILL)
        middle.wait(timeout=5)
        while _alive(int(pid)) and time.monotonic() < killed + 1.0:
            time.sleep(0.01)
        assert not _alive(int(pid)), "the grandchild outlived its parent by 1 s"
    finally:
        middle.kill()


def test_a_child_whose_parent_is_already_gone_exits_at_once() -> None:
    # the pid the child was told is not its parent's: the parent died before prctl was set
    code = "from core.process import die_with_parent; die_with_parent(1 << 30); print('ran on')"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=ENV, cwd=REPO, timeout=30
    )
    assert out.returncode == 0 and "ran on" not in out.stdout
