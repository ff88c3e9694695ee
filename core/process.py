"""Child processes that never outlive the process that started them.

A ``wm run`` killed with SIGKILL runs no cleanup, so its children (the log decoder, the
odometry process) must notice on their own. :func:`die_with_parent`, called first thing in a
child, asks the Linux kernel to send the child a signal when its parent goes (``prctl
PR_SET_PDEATHSIG``) and closes the race where the parent died before the call. Elsewhere it
does nothing and the children's other guards (end of their pipe, :func:`exit_with_parent`'s
thread watching the parent's pid) remain the way out.

The kernel sends the signal when the *thread* that forked the child exits, not only the
process: start such children from a thread that lives as long as they are needed (the node's
feeding thread, the main thread of ``wm run``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import threading
import time

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(parent: int | None, sig: int = signal.SIGKILL) -> bool:
    """Have the kernel send ``sig`` to this process when its parent dies; return whether it
    could (False off Linux or without a usable libc).

    ``parent`` is the pid of the process meant to be the parent, taken *before* the fork or
    spawn (the child cannot know it otherwise): if it is gone already, the child was
    re-parented before the kernel could be told, and this process exits at once (status 0).
    None skips that check."""
    armed = _set_pdeathsig(sig)
    if parent is not None and os.getppid() != parent:
        os._exit(0)  # the parent died before prctl: no signal will ever come
    return armed


def _set_pdeathsig(sig: int) -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):  # no libc to load, or one without prctl
        return False


def exit_with_parent(parent: int, name: str, period_s: float = 0.5) -> None:
    """Start a daemon thread ``name`` that ends this process (status 0) as soon as ``parent``
    (its pid, taken before the fork or spawn) is no longer its parent, checking every
    ``period_s`` s: the guard where :func:`die_with_parent` could not arm the kernel's
    signal. A thread, since the main thread may be blocked anywhere, even on a request the
    parent was killed while writing."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period_s)
        os._exit(0)

    threading.Thread(target=watch, name=name, daemon=True).start()
