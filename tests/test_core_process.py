"""core.process: a child that called die_with_parent dies with its parent (Linux), a child
whose parent died before the call exits at once, and a child that only started
exit_with_parent's thread (no kernel signal) exits soon after its parent."""

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
# the same with only the watching thread: the grandchild prints its pid and sleeps
MIDDLE_WATCH = MIDDLE.replace("die_with_parent(int(sys.argv[1]))", "None").replace(
    "from core.process import die_with_parent",
    "from core.process import exit_with_parent; exit_with_parent(int(sys.argv[1]), 'w', 0.05)",
)


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _grandchild_outlives_sigkill(middle_code: str) -> tuple[str, bool]:
    """Start ``middle_code``, read its grandchild's pid and second word, SIGKILL the middle
    process: (that word, whether the grandchild still ran 1 s later)."""
    middle = subprocess.Popen(
        [sys.executable, "-c", middle_code], stdout=subprocess.PIPE, text=True, env=ENV, cwd=REPO
    )
    try:
        assert middle.stdout is not None
        pid, word = middle.stdout.readline().split()
        assert _alive(int(pid))
        killed = time.monotonic()
        middle.send_signal(signal.SIGKILL)
        middle.wait(timeout=5)
        while _alive(int(pid)) and time.monotonic() < killed + 1.0:
            time.sleep(0.01)
        outlived = _alive(int(pid))
        if outlived:
            os.kill(int(pid), signal.SIGKILL)
        return word, outlived
    finally:
        middle.kill()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_child_dies_within_a_second_of_its_parents_sigkill() -> None:
    armed, outlived = _grandchild_outlives_sigkill(MIDDLE)
    assert armed == "True"
    assert not outlived, "the grandchild outlived its parent by 1 s"


def test_a_child_watching_its_parent_exits_within_a_second_of_its_sigkill() -> None:
    _, outlived = _grandchild_outlives_sigkill(MIDDLE_WATCH)
    assert not outlived, "the grandchild outlived its parent by 1 s"


def test_a_child_whose_parent_is_already_gone_exits_at_once() -> None:
    # the pid the child was told is not its parent's: the parent died before prctl was set
    code = "from core.process import die_with_parent; die_with_parent(1 << 30); print('ran on')"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=ENV, cwd=REPO, timeout=30
    )
    assert out.returncode == 0 and "ran on" not in out.stdout
